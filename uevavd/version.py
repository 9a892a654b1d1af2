"""The package's version, in a leaf module every layer may import (``uevavd.__version__``)."""

__version__ = "0.1.0"
