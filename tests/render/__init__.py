"""Tests of qr_cl.render: the public calls, autograd, the selection cache, renders split by buffer limits."""
