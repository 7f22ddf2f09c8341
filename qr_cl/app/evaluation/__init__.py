"""Open-vocabulary 3D segmentation of Gaussians: ground truth, predictions, mIoU/mAcc, pictures, and
the ``qr-cl eval`` command (:mod:`.command`)."""
