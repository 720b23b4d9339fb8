"""Policy kinds beyond sac_mlp, one module each (flow_vla, smolvla); each registers itself on import."""
