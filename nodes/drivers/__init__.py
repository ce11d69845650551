"""Hardware backends behind small interfaces: stage, display/trigger, camera."""
