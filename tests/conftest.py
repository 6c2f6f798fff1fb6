"""Test-session settings.

Hypothesis draws new examples on every local run (and keeps the failing
ones in ``.hypothesis/``); CI runs with the ``ci`` profile
(``HYPOTHESIS_PROFILE=ci``, set by ``.ci/run``), derandomized so that the same
commit gives the same verdict. An example that once failed is added to its
test with ``@example`` so that CI keeps checking it.
"""

import os

from hypothesis import settings

settings.register_profile("ci", derandomize=True, print_blob=True)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "default"))
