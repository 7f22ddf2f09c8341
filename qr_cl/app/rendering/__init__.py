"""Pictures of a scene's RGB, depth and alpha: the ``qr-cl render`` command (:mod:`.command`)."""
