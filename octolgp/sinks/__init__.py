"""Where map events go: the sink protocol, the null sink and the Rerun sink."""
