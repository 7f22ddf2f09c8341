"""Tests of qr_cl.app: scene folders, synthetic rooms, training, evaluation, reproduce, bench, the CLI."""
