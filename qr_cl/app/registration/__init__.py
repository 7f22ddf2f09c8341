"""Dr.Splat's training-free registration: mask features onto the Gaussians through each pixel's
top contributors (:mod:`.register`, its float64 twin in tests/app/register_twin.py, the command ``qr-cl
register`` in :mod:`.command`)."""
