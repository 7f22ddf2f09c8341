"""Tests of qr_cl.runtime: device choice and self-check, kernel signatures, memory pools."""
