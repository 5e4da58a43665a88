"""``python -m thetahat``: the same as the ``thetahat`` command (:mod:`thetahat.cli`)."""

from .cli import main

raise SystemExit(main())
