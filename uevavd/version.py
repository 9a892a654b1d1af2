"""The package's version, in a leaf module every layer may import (``uevavd.__version__``)."""

__version__ = "0.1.0"
"""The installed uevavd's version (PEP 440), recorded in every run and policy file."""
