"""filterpy's ``ExtendedKalmanFilter``, imported from its own module and nothing else of filterpy.

``import filterpy.kalman`` runs the package's ``__init__``, which imports every filter it has (UKF, IMM,
ensemble, square root, ...) and with them ``scipy.stats`` and ``scipy.ndimage``: about 80 % of an agent's
start-up (1.2 of 1.5 CPU seconds here, ``python -X importtime -c "import stack.agents.cli"``) and tens of MB
resident, in every robot's process, for one class. Its module ``filterpy/kalman/EKF.py`` needs only numpy,
``scipy.linalg``, ``filterpy.common.helpers`` (``pretty_str``, ``reshape_z``) and ``filterpy.stats.logpdf``
(used by its ``log_likelihood`` property alone).

So :func:`extended_kalman_filter` loads that module under its real name with its parent packages standing in
as bare packages (their real folders, their ``__init__`` not run) and ``logpdf`` deferred to the real one on
first use, then takes the stand-ins out of ``sys.modules``: a later ``import filterpy.kalman`` runs the real
``__init__``s, which find the loaded ``EKF`` module and reuse it, so the class is the same object either way.
If filterpy is already imported, its class is returned as it is. ``tests/test_estimation.py`` checks both.
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
import types

_PACKAGES = ("filterpy", "filterpy.common", "filterpy.stats", "filterpy.kalman")


def _bare_package(name: str) -> types.ModuleType:
    spec = importlib.util.find_spec(name)  # a subpackage's spec: its parent must be in sys.modules already
    if spec is None or not spec.submodule_search_locations:
        raise ImportError(f"{name} is not installed")
    mod = types.ModuleType(name)
    mod.__path__ = list(spec.submodule_search_locations)
    mod.__spec__ = spec
    return mod


def _logpdf(*args, **kwargs):
    """filterpy.stats.logpdf, imported (with scipy.stats) when first called."""
    from filterpy.stats import logpdf

    return logpdf(*args, **kwargs)


def extended_kalman_filter() -> type:
    """The class ``filterpy.kalman.ExtendedKalmanFilter``, without importing the rest of filterpy."""
    if "filterpy.kalman" in sys.modules:
        return sys.modules["filterpy.kalman"].ExtendedKalmanFilter
    installed = []
    try:
        for name in _PACKAGES:
            sys.modules[name] = _bare_package(name)
            installed.append(name)
        helpers = importlib.import_module("filterpy.common.helpers")
        sys.modules["filterpy.common"].pretty_str = helpers.pretty_str
        sys.modules["filterpy.common"].reshape_z = helpers.reshape_z
        sys.modules["filterpy.stats"].logpdf = _logpdf
        return importlib.import_module("filterpy.kalman.EKF").ExtendedKalmanFilter
    finally:
        for name in installed:
            del sys.modules[name]
