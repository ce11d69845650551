"""The light-transport model (scenes, single scattering, polarization, sensor) and the simulator."""
