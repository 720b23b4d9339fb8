"""Built-in tasks, one module each; `edge_agent.task.TASKS` imports every module here on first use."""
