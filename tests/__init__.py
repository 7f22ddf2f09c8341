"""qr-cl's tests, one folder per package layer (runtime, scene, stages, render, backbone, app) and
drivers/ for the OpenCL implementations; helpers are imported as ``tests.<module>``."""
