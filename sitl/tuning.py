"""Filter tuning derived from a scenario's sensor models: the filter is told the noise levels the
simulator uses (converted to the filter's continuous-time densities), nothing more.

Conversions (documented because the simulator and the filter speak different units):
* white noise given as a uniform half-width ``w`` per sample at rate f: sigma = w/sqrt(3) per
  sample, density = sigma / sqrt(f)  (rad/sqrt(s) or m/s/sqrt(s));
* a 1st-order Gauss-Markov bias instability (sigma, tau) is covered by a bias random walk of
  density sigma*sqrt(2/tau) (the GM's own driving noise);
* initial bias uncertainty = sqrt(fixed^2 + turn-on^2 + instability^2) per axis.
"""
from __future__ import annotations

import math

from companion.nav.base_check import BASE_POSITION_MAX_SPP_DIFF_M
from companion.nav.filter import ProcessNoise

from .paper import FilterTuning


def tuning_for(scenario) -> FilterTuning:
    imu = scenario.imu
    f = imu.rate_hz
    arw = imu.gyro_arw_radps_per_sqrthz or imu.gyro_noise_uniform_radps / math.sqrt(3.0) / math.sqrt(f)
    vrw = imu.accel_vrw_mps2_per_sqrthz or imu.accel_noise_uniform_mps2 / math.sqrt(3.0) / math.sqrt(f)
    bg_rw = imu.gyro_bi_sigma_radps * math.sqrt(2.0 / imu.gyro_bi_tau_s) if imu.gyro_bi_sigma_radps else 1e-9
    ba_rw = imu.accel_bi_sigma_mps2 * math.sqrt(2.0 / imu.accel_bi_tau_s) if imu.accel_bi_sigma_mps2 else 1e-7
    bg0 = math.sqrt(imu.gyro_bias_fixed_radps ** 2 + imu.gyro_bias_sigma_radps ** 2 + imu.gyro_bi_sigma_radps ** 2)
    ba0 = math.sqrt(imu.accel_bias_fixed_mps2 ** 2 + imu.accel_bias_sigma_mps2 ** 2 + imu.accel_bi_sigma_mps2 ** 2)
    clk = scenario.rover_clock
    # a steered clock: its drift moves with the steering loop; white-FM and RW-FM densities plus
    # the loop's own motion (drift rate ~ bias/tau^2) are covered by a generous drift density
    noise = ProcessNoise(gyro_arw_rad_per_sqrt_s=arw, accel_vrw_mps_per_sqrt_s=vrw,
                         gyro_bias_rw_radps_per_sqrt_s=bg_rw, accel_bias_rw_mps2_per_sqrt_s=ba_rw,
                         clock_bias_psd_m2ps=max(clk.s_f, 0.01), clock_drift_psd_m2ps3=max(clk.s_g, 0.1))
    # initial attitude: the paper starts from a known attitude (navigation-grade alignment); a
    # drone starts from its autopilot's attitude: levelled to a few mrad, heading from a compass (~3 deg)
    paper_like = scenario.name.startswith("paper")
    p0 = {"tilt_rad": 1e-3 if paper_like else 5e-3, "heading_rad": 1e-3 if paper_like else 0.05,
          "pos_m": 0.5, "vel_mps": 0.05,
          "ba_mps2": max(ba0, 1e-3), "bg_radps": max(bg0, 1e-6), "clk_m": 100.0, "drift_mps": 5.0}
    rx = scenario.rover_rx
    # Selective Availability (paper scenario only) is far larger than any per-satellite error model:
    # standalone modes are told the whole Table-1 budget, and the SA rate enters the Doppler
    slow = [scenario.iono, scenario.tropo, scenario.sat_clock, scenario.sa]
    standalone_floor = 0.0
    sigma_doppler = max(rx.doppler_noise_mps, 0.05) * 2.0
    if scenario.sa.sigma_common_m > 0:
        var = sum(e.sigma_common_m ** 2 + e.sigma_diff_m ** 2 for e in slow)
        var += scenario.orbit.sigma_los_common_m ** 2 + scenario.orbit.sigma_los_diff_m ** 2
        var += rx.code_noise_m ** 2 + rx.code_mp_m ** 2
        standalone_floor = math.sqrt(var)
        sa_rate = scenario.sa.sigma_common_m / scenario.sa.tau_s
        sigma_doppler = math.hypot(sigma_doppler, sa_rate)
    klobuchar = None
    if any(scenario.klobuchar_alpha) or any(scenario.klobuchar_beta):
        klobuchar = (tuple(scenario.klobuchar_alpha), tuple(scenario.klobuchar_beta))
    return FilterTuning(noise=noise, p0=p0, sigma_doppler_mps=sigma_doppler, klobuchar=klobuchar,
                        pseudorange_correlation_time_s=rx.code_mp_tau_s,
                        # a drone sits still on the ground before take-off; the paper's vehicle never rests
                        zupt_enabled=not paper_like,
                        sigma_phase_elevation_scaling=rx.el_scaling,
                        sigma_pseudorange_standalone_floor_m=standalone_floor,
                        base_max_spp_diff_m=max(BASE_POSITION_MAX_SPP_DIFF_M, 20.0 * standalone_floor),
                        # TDCP differences consecutive epochs: of the multipath only what changed in
                        # an epoch interval (1 s) is left, 2 (1 - rho) of its variance instead of 2
                        sigma_phase_m=math.hypot(rx.carrier_noise_m, rx.carrier_mp_m * math.sqrt(
                            1.0 - math.exp(-1.0 / rx.carrier_mp_tau_s)) if rx.carrier_mp_tau_s > 0 else rx.carrier_mp_m),
                        sigma_tdcp_floor_mps=0.005,
                        gnss_latency_s=0.0 if scenario.name == "paper" else 0.08)

