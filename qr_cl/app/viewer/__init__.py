"""The web viewer of ``qr-cl view``: frames rendered by qr-cl on request (:mod:`.frames`), its
cameras (:mod:`.views`), a standard-library HTTP server (:mod:`.server`), the page (``static/``)
and the command (:mod:`.command`)."""
