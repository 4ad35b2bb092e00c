"""The differential ionosphere of a rover-base pair as states: one between-receiver
single-difference slant delay per satellite, in metres on GPS L1's frequency (RTKLIB's
``IONOOPT_EST``), the model of the engine's RTK (:mod:`companion.nav.rtk_update`) and, when
asked (``RtkConfig.iono_states``, ``companion gnss --mode rtk --iono est``), of the
post-processing RTK (:mod:`.rtk`; README: on a 5.3-km car it puts the fixed track on the
ionosphere-free solution of its integers, 4.5 cm from the default's).

* On a carrier of wavelength ``lambda`` the delay is ``(lambda / lambda_L1)^2`` of it
  (:func:`iono_factor`): subtracted from the phase (it advances), added to the code.
* Prior at acquisition (zero mean): the zenith sigma ``zenith_m + ppm x baseline`` taken to the
  slant by the single-layer model (shell at 350 km, :func:`slant_factor`).
* In time: a random walk with the PSD of a first-order Markov process of that sigma and
  ``correlation_time_s`` (:func:`random_walk_psd`).
"""
from __future__ import annotations

import math

from ..messages import GPS_L1_HZ, SPEED_OF_LIGHT_MPS

L1_WAVELENGTH_M = SPEED_OF_LIGHT_MPS / GPS_L1_HZ
EARTH_RADIUS_M, IONO_SHELL_M = 6371e3, 350e3


def iono_factor(wavelength_m):
    """The ionospheric delay on a carrier of ``wavelength_m`` per metre of it on L1's: (f_L1/f)^2."""
    return (wavelength_m / L1_WAVELENGTH_M) ** 2


def slant_factor(elevation_rad: float) -> float:
    """Slant over vertical delay of the single-layer ionosphere (shell at 350 km)."""
    x = EARTH_RADIUS_M / (EARTH_RADIUS_M + IONO_SHELL_M) * math.cos(elevation_rad)
    return 1.0 / math.sqrt(1.0 - x * x)


def prior_sigma_m(elevation_rad: float, baseline_m: float, zenith_m: float, ppm: float) -> float:
    """The slant delay's sigma at acquisition: ``(zenith_m + ppm 1e-6 baseline) x slant factor``."""
    return (zenith_m + ppm * 1e-6 * baseline_m) * slant_factor(elevation_rad)


def random_walk_psd(sigma_m: float, correlation_time_s: float) -> float:
    """PSD (m^2/s) of the random walk standing for a first-order Markov process of ``sigma_m``."""
    return 2.0 * sigma_m ** 2 / correlation_time_s


__all__ = ["L1_WAVELENGTH_M", "iono_factor", "slant_factor", "prior_sigma_m", "random_walk_psd"]
