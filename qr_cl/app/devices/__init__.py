"""The OpenCL devices qr-cl can use: the ``qr-cl devices`` command (:mod:`.command`)."""
