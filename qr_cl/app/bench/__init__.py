"""Kernel benchmarks (``qr-cl bench``): the sweep's jobs and their timings, the device's limits,
the complexity fit, the report and its plots, and the side-by-side run on every implementation."""
