"""GS-Net training through a feature renderer: configuration, the network, the rays of a step and
their selections, the contrastive loss, the training loop, and free per-Gaussian features fitted through the renderer;
the ``qr-cl train`` command (:mod:`.command`)."""
