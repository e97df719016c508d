"""The corruption injector: sixteen families on one physical ladder (SPEC section 3).

numpy + OpenCV only. `registry` holds the declarations, one module per family group holds the operators,
`seeding` derives every random realisation, `api` is the public entry, `hooks` reaches foreign loaders.
"""

from .api import corrupt, corrupt_sample
from .ladder import FAMILIES, QUALITY_FAMILIES, SEVERITIES, SPEC_VERSION

__all__ = ["FAMILIES", "QUALITY_FAMILIES", "SEVERITIES", "SPEC_VERSION", "corrupt", "corrupt_sample"]
