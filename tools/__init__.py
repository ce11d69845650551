"""The command line and the tools on top of the rig: topic, record, replay, bag, view, Foxglove, render."""
