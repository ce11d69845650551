"""Benchmarks that print tables (``polarstripe bench NAME``, ``--json`` for machines)."""
