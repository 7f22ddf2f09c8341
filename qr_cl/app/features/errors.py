"""The one error type of ``qr-cl features``."""
from __future__ import annotations


class FeaturesError(ValueError):
    """Input ``qr-cl features`` cannot use; the message names the file and what is wrong (one line)."""
