"""OpenCL C sources of qr-cl, shipped as package data (read with importlib.resources)."""
