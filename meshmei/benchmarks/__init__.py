"""Benchmarks that write tables to ``docs/benchmarks.md`` (run as ``python -m meshmei.benchmarks.<name>``)."""
