"""The rig's nodes (emitter, grabber, polarizer, compositor, planner) and their runtime."""
