"""Tests of qr_cl.backbone (backbone/): sparse tensors, convolutions, voxelization, GSNet."""
