"""Dr.Splat's training-free registration: mask features onto the Gaussians through each pixel's
top contributors (:mod:`.register`, its float64 twin :mod:`.register_ref`, the command ``qr-cl
register`` in :mod:`.command`)."""
