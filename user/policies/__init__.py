"""Built-in policy kinds: each module registers with user.policy.POLICIES (found without an import list)."""
