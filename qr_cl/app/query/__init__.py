"""Asking a scene a question: query text to a text embedding (:mod:`.text`), per-Gaussian
relevancy (:mod:`.relevancy`), the scene and its per-Gaussian features (:mod:`.scene`),
heatmaps and PLYs (:mod:`.pictures`), and the ``qr-cl query`` command (:mod:`.command`)."""
