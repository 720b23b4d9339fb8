"""Built-in robots; importing this package registers them."""

from edge_agent.robots import gym_hil_panda, lang_reach, sim_arm  # noqa: F401 - gym_hil_panda registers only if gym-hil imports
