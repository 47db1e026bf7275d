"""``import ppr.shapes`` keeps working: this module is :mod:`ppr.geometry.shapes` itself."""

import sys

from .geometry import shapes as _shapes

sys.modules[__name__] = _shapes
