"""Benchmarks and evidence: the figures docs/measurements.md and docs/performance.md quote."""
