"""Built-in policy networks, one module per kind (mlp, cnn); each registers with user.policy.register_policy."""
