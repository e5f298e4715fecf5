from .core import *  # noqa: F401,F403
from .core import __all__
from .pixel import *  # noqa: F401,F403
from .pixel import __all__ as _pixel_all

__all__ = list(__all__) + list(_pixel_all)
