"""``python -m sagrasp_jax.sysid``: fit the lagged servo model to a logged arm motion (jax-free).

The fit is :mod:`sagrasp_jax.deploy.sysid`; this is its command.
"""

from __future__ import annotations

import sys

if __name__ == "__main__":
    from sagrasp_jax.deploy.sysid import main

    sys.exit(main())
