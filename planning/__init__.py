"""The planner (optimal camera-source placement), its command line, and the paper's experiments (compare, figures)."""
