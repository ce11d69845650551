"""The node runtime: bus, Node base class, launcher, recorder/replayer, command line."""
