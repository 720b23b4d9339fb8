"""Built-in tasks: each module registers its kinds with edge_agent.task.TASKS (found without an import list)."""
