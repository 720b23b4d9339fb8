"""Built-in teleoperators, one module each; `edge_agent.teleop.TELEOPERATORS` imports every module here on first use."""
