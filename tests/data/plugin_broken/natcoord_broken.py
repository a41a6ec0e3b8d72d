"""A plug-in whose import fails (its engine is missing)."""

import natcoord_no_such_engine  # noqa: F401

NAME = "broken"
