"""``qr-cl features``: LangSplat's per-view CLIP mask features (``language_features/<img>_s.npy``
and ``<img>_f.npy``) made from a scene's images with SAM's automatic masks and OpenCLIP's image
encoder, in plain torch on any torch device (optional extra: ``pip install -e ".[features]"``)."""
