"""Tests of qr_cl.scene: scene files and cameras."""
