"""The unit of the numbers polrig's commands write: ADC DN.

A 12-bit ADC read out as Mono16 delivers its codes times 16 (and its black level 16 becomes
256), as ``polrig sim render`` and a GenICam camera in Mono16 do; the noise model, the truth of a
simulated capture and every result of ``polrig capture`` are in the ADC's own DN
(:func:`polrig.app.processing.adc_scale`). The commands that read a raw file (``stokes``, ``infer``)
convert its values with the same factor, so their Stokes and Mueller images are in ADC DN
whatever the file's pixel format and can be compared with a truth file or a session's results.
"""

from __future__ import annotations

from polrig.formats.config import RigConfig
from polrig.sensor.noise import SensorModel


def config_sensor_model(config: RigConfig) -> SensorModel:
    """The camera's noise model for a rig configuration: its ``[sensor_model]`` table, else the
    simulated camera's (``[sim] sensor_model`` over :data:`polrig.sim.options.SENSOR_MODEL_DEFAULTS`)
    for a simulated camera, else the IMX250 defaults of :class:`SensorModel`."""
    if config.sensor_model:
        return SensorModel(**config.sensor_model)
    if config.driver("camera") == "sim":
        from polrig.sim.options import SENSOR_MODEL_DEFAULTS

        sim_table = config.get("sim") or {}
        return SensorModel(**{**SENSOR_MODEL_DEFAULTS, **(sim_table.get("sensor_model") or {})})
    return SensorModel()


def adc_factor(config: RigConfig, bit_depth: int) -> tuple[SensorModel, float]:
    """``(model, factor)``: the noise model and the factor from a file's DN (``bit_depth``
    significant bits) to ADC DN (:func:`polrig.app.processing.adc_scale`)."""
    from polrig.app.processing import adc_scale

    model = config_sensor_model(config)
    return model, adc_scale(model, bit_depth)
