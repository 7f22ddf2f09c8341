"""Scene files from one format to another: the ``qr-cl convert`` command (:mod:`.command`)."""
