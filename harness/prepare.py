"""Old home of dataset preparation, kept so existing imports (``from harness.prepare import prepare``) work: the
prepared cache is the ``harness.cache`` package, whose public names this module re-exports."""

from harness.cache import *  # noqa: F403 - every public name of harness.cache, as listed in its __all__
from harness.cache import __all__  # noqa: F401 - the same list
