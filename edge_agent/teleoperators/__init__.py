"""Built-in teleoperators: each module registers with edge_agent.teleop.TELEOPERATORS (found without an import list)."""
