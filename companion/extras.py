"""Optional dependencies: import them where they are used, or fail naming the extra that installs them.

The service itself needs only the core dependencies (``pip install companion``); plotting, MQTT and
the simulator are extras (``pyproject.toml``)::

    plot = matplotlib (every --plot)      mqtt = aiomqtt (telemetry, corrections.source = 'mqtt')
    sitl = the simulator (pyubx2, plots)  rinex = hatanaka (compressed RINEX)
    ulog = pyulog (PX4 .ulg replay)      receiver = pyubx2 (companion gnss configure)
    kernels = numba (compiled IMU-rate and LAMBDA kernels)
    rtklib = pyrtklib5 (RTKLIB demo5 beside companion gnss --mode rtk: --against-demo5)
    test = everything the test suite needs

``require("aiomqtt", "mqtt", "MQTT telemetry")`` returns the module, or raises :class:`MissingExtra`
(an ImportError) saying ``MQTT telemetry needs aiomqtt, which is not installed: pip install
'companion[mqtt]'``.  The command line prints that message and exits 2 instead of a traceback.
"""
from __future__ import annotations

import importlib
import importlib.util
from types import ModuleType

# module -> extra that installs it (pyproject.toml [project.optional-dependencies])
EXTRA_OF = {"matplotlib": "plot", "aiomqtt": "mqtt", "pyubx2": "sitl", "georinex": "test", "hatanaka": "rinex", "pyulog": "ulog", "numba": "kernels",
            "pyrtklib5": "rtklib"}


class MissingExtra(ImportError):
    """An optional dependency is not installed; the message names the pip command that installs it."""


def install_hint(module: str, extra: str | None = None) -> str:
    extra = extra or EXTRA_OF.get(module.partition(".")[0], "")
    return f"pip install 'companion[{extra}]'" if extra else f"pip install {module.partition('.')[0]}"


def available(module: str) -> bool:
    """Whether ``module`` (top-level name) can be imported, without importing it."""
    try:
        return importlib.util.find_spec(module.partition(".")[0]) is not None
    except (ImportError, ValueError):
        return False


def require(module: str, extra: str | None = None, purpose: str = "") -> ModuleType:
    """Import ``module``; if it (not one of its own imports) is missing, raise :class:`MissingExtra`."""
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as exc:
        top = module.partition(".")[0]
        if exc.name not in (top, module):
            raise                                  # the package is there but broken: show the real error
        what = f"{purpose} needs {top}" if purpose else f"{top} is required"
        raise MissingExtra(f"{what}, which is not installed: {install_hint(module, extra)}") from None


def pyplot(purpose: str = "plotting") -> ModuleType:
    """matplotlib.pyplot on the headless Agg backend, or :class:`MissingExtra` naming ``[plot]``."""
    mpl = require("matplotlib", "plot", purpose)
    mpl.use("Agg")
    return require("matplotlib.pyplot", "plot", purpose)


__all__ = ["EXTRA_OF", "MissingExtra", "available", "install_hint", "pyplot", "require"]
