"""The embedded default job, end to end on synthetic labelled rooms: the ``qr-cl demo`` command (:mod:`.command`)."""
