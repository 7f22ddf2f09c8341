"""Kernel benchmarks (``qr-cl bench``): the sweep's jobs and their timings, the device's limits,
the complexity fit, the report and its plots, the side-by-side run on every implementation, and
the command and its subcommands (:mod:`.command`)."""
