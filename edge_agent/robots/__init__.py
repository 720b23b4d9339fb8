"""Built-in robots, one module each; `edge_agent.robot.ROBOTS` imports every module here on first use."""
