"""Built-in robots; importing this package registers them."""

from edge_agent.robots import sim_arm  # noqa: F401
