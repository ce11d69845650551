"""The planner (optimal camera-source placement), its command line, sweeps, and the paper's experiments
(compare, figures)."""
