"""Input and output: the session format, capture, sinks, Rerun view and printing."""
