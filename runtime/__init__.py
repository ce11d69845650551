"""The framework: bus, services, the Node base and its bus protocol, params, launcher, graph, testing."""
