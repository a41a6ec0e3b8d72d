"""An engine plug-in for natcoord: natcoord's own solver with fixed-step RK4 (index-1
formulation, projection) under the name ``rk4``. It follows natcoord's adapter contract
(natcoord.engines.base.Adapter): NAME, PACKAGE, SETTINGS, CAPABILITIES, version(), run().
Importing this module imports no engine."""

from natcoord.engines.capabilities import Capabilities
from natcoord.engines.schema import Setting, defaults

NAME = "rk4"  # the entry point's name: case files, --engines, results
PACKAGE = "natcoord-rk4"  # what `pip install` needs when version() cannot import it
SETTINGS = (Setting("dt", "number", 1e-3, "time step; must divide the output interval",
                    "s", exclusive_minimum=0.0),)
CAPABILITIES = Capabilities(dimensions={2}, drivers=(), loops="rigid",
                            why={"drivers": "this example prescribes no motion"})


def version() -> str:
    from importlib.metadata import version as dist_version

    return dist_version(PACKAGE)  # PackageNotFoundError is an ImportError: "skipped"


def run(case, init, settings):
    """Simulate ``case`` from ``init`` at its sample times; a natcoord EngineRun."""
    from natcoord.engines import natcoord_engine

    s = {**defaults(SETTINGS), **settings}
    result = natcoord_engine.run(case, init, {"method": "rk4", "h": s["dt"]})
    result.settings = s
    return result
