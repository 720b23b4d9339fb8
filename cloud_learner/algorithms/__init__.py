"""Built-in algorithms: each module registers with cloud_learner.algorithm.ALGORITHMS (found without an import list)."""
