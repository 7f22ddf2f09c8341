"""Every OpenCL implementation install.sh installs (parity with PoCL), oclgrind, and drivers' wrong answers."""
