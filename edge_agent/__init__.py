"""Edge agent: the daemon on each robot PC."""
