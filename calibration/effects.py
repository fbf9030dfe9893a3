"""The effect catalogue: what a nominal model may lack, each with a "no effect" value.

Every effect has a primary parameter (the one whose bootstrap interval must exclude the
no-effect value before the effect is accepted), the data it needs, the diagnostic plot
that shows it, and the effects it is easily confused with (look-alikes) together with the
excitation that would tell them apart.

Units: ``u`` = command units of the log (e.g. V), ``x`` = position units (e.g. m),
accelerations in x-units/s² (the axis model is identified in normalized form, i.e. forces
divided by the inertia J).
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class EffectSpec:
    """One catalogue entry.

    Attributes:
        name: catalogue name used in reports.
        description: what it models (one line).
        primary: name of the primary parameter.
        unit: unit of the primary parameter.
        no_effect: value of the primary parameter meaning "no effect" (inf for saturation).
        needs: data channels it needs ("v" measured velocity, "vbat", "m" payload).
        diagnostic: what the diagnostic plot shows.
        absorbed_by_nominal: set when the nominal axis model already has this term and refits it.
    """

    name: str
    description: str
    primary: str
    unit: str
    no_effect: float
    needs: tuple[str, ...] = ()
    diagnostic: str = ""
    absorbed_by_nominal: str = ""
    #: +1 when only a positive primary parameter has the physical meaning (a back-EMF that
    #: lowers the drive as speed rises); an interval wholly on the other side is rejected
    physical_sign: int = 0


CATALOGUE: dict[str, EffectSpec] = {
    e.name: e
    for e in [
        EffectSpec("delay", "pure transport delay of the command", "delay_s", "s", 0.0,
                   diagnostic="cross-correlation of the nominal residual with the command rate"),
        EffectSpec("actuator_lag", "first-order lag between command and force (time constant)",
                   "tau_s", "s", 0.0,
                   diagnostic="cross-correlation of the nominal residual with the command rate"),
        EffectSpec("deadband", "commands with |u| below a width produce no force",
                   "width_u", "u", 0.0, diagnostic="residual vs command"),
        EffectSpec("backlash", "play (hysteresis) of half-width h between command and force",
                   "halfwidth_u", "u", 0.0, diagnostic="residual vs command, split by command direction"),
        EffectSpec("load_backlash", "play of half-width h between the driven motor and the measured (load) "
                   "position: at every motion reversal the load stands still until the motor has crossed the gap",
                   "halfwidth_x", "x", 0.0,
                   diagnostic="open-loop position error after motion reversals (a step of 2h per reversal)"),
        EffectSpec("coulomb_friction", "constant friction opposing motion, Fc/J·sign(v)",
                   "fc_acc", "x/s^2", 0.0, diagnostic="residual vs velocity"),
        EffectSpec("stribeck_friction", "extra breakaway friction decaying with speed, (Fs-Fc)/J·exp(-(v/vs)^2)",
                   "fs_extra_acc", "x/s^2", 0.0, diagnostic="residual vs velocity (near zero)"),
        EffectSpec("asymmetric_friction", "direction-dependent Coulomb friction: fc + fa forward, fc - fa "
                   "backward (fa on top of the accepted Coulomb level fc)", "fa_acc", "x/s^2", 0.0,
                   diagnostic="residual vs velocity, by direction"),
        EffectSpec("gravity_load", "position-dependent load -gl·sin(x - q0), e.g. gravity on a rotary joint "
                   "(x in rad, q0 the hanging angle)", "gl_acc", "x/s^2", 0.0,
                   diagnostic="residual vs position"),
        EffectSpec("cogging", "position-periodic load -gc·sin(k·x - phi) (cogging, detent; k = n per revolution "
                   "when x is in rad), k estimated from at least two periods over the stroke", "gc_acc", "x/s^2", 0.0,
                   diagnostic="residual vs position (periodogram of the residual over k)"),
        EffectSpec("viscous_friction", "friction proportional to velocity, b/J·v",
                   "c_per_s", "1/s", 0.0, diagnostic="residual vs velocity",
                   absorbed_by_nominal="c = b/J is a nominal parameter of the axis model and is refit "
                                       "with every candidate, so a viscous error is a tuning error, not an effect"),
        EffectSpec("force_offset", "constant force (e.g. cable drag, bias in the amplifier), d/J",
                   "offset_acc", "x/s^2", 0.0, diagnostic="mean residual"),
        EffectSpec("back_emf", "drive force that falls with speed while driven, (a - kemf·v)·u (back-EMF of a "
                   "PWM-driven DC motor: it opposes the supply only during the on-time, a share u of the period)",
                   "kemf", "x/s^2 per (u·x/s)", 0.0, diagnostic="residual vs command × velocity",
                   physical_sign=1),
        EffectSpec("battery_sag", "actuator gain scales with measured supply voltage: (1+k(vbat-vref)/vref)",
                   "gain_per_rel_v", "1", 0.0, needs=("vbat",), diagnostic="residual vs battery voltage"),
        EffectSpec("saturation", "command clipped at ±limit", "limit_u", "u", float("inf"),
                   diagnostic="residual vs command (large |u|)"),
        EffectSpec("payload_mass", "inertia grows with the logged payload: J·(1+mu·m)",
                   "mu_per_unit", "1/m-unit", 0.0, needs=("m",),
                   diagnostic="residual vs acceleration, split by payload"),
        EffectSpec("slope", "gravity load on an inclined axis, g·sin(theta) (independent of payload)",
                   "gravity_acc", "x/s^2", 0.0, diagnostic="mean residual"),
        EffectSpec("sensor_bias", "velocity sensor bias against the position encoder", "bias_v", "x/s", 0.0,
                   needs=("v",), diagnostic="measured velocity vs position derivative"),
        EffectSpec("sensor_scale", "velocity sensor scale against the position encoder", "scale_v", "1", 1.0,
                   needs=("v",), diagnostic="measured velocity vs position derivative"),
    ]
}

#: Look-alike pairs and the excitation that separates them.
LOOK_ALIKES: dict[frozenset, str] = {
    frozenset({"coulomb_friction", "deadband"}):
        "slow ramps through zero velocity at several command levels (friction depends on the sign of "
        "velocity, a deadband on the size of the command)",
    frozenset({"coulomb_friction", "stribeck_friction"}):
        "constant-velocity runs at several low speeds (the Stribeck term decays with speed)",
    frozenset({"delay", "actuator_lag"}):
        "sharp command steps or a high-frequency chirp (a delay shifts the response rigidly, a lag rounds it)",
    frozenset({"force_offset", "slope"}):
        "runs with a different payload or at another inclination (gravity load scales with mass, an offset "
        "does not)",
    frozenset({"backlash", "deadband"}):
        "command reversals away from zero, e.g. a sine on an offset (backlash acts at every reversal)",
    frozenset({"load_backlash", "backlash"}):
        "command reversals while the axis keeps moving one way, and motion reversals under a steady command "
        "(play on the command acts at command reversals, play before the load at motion reversals)",
    frozenset({"load_backlash", "delay"}):
        "slow motion reversals (load-side play holds the position for a distance, a delay for a time)",
    frozenset({"backlash", "coulomb_friction"}):
        "command reversals while the axis keeps moving in one direction",
    frozenset({"saturation", "deadband"}):
        "commands spread evenly over the whole range, large and small",
    frozenset({"force_offset", "coulomb_friction"}):
        "motion in both directions at similar speeds for similar durations",
    frozenset({"sensor_bias", "force_offset"}):
        "long runs at zero velocity (a velocity bias shows while standing still)",
    frozenset({"asymmetric_friction", "coulomb_friction"}):
        "motion in both directions at similar speeds (the asymmetry is the difference between them)",
    frozenset({"asymmetric_friction", "force_offset"}):
        "none on the axis alone while the offset is below the Coulomb level: Coulomb friction fc plus an offset "
        "-fa moves, sticks and breaks away exactly as friction fc ± fa by direction for every command; a force "
        "sensor, or a run with the load turned round (an offset from gravity or a cable changes sign, friction "
        "does not)",
    frozenset({"gravity_load", "force_offset"}):
        "motion over a wider range of positions (a gravity load changes with the angle, an offset does not)",
    frozenset({"cogging", "gravity_load"}):
        "motion over more positions, several revolutions if the joint can (a gravity load has one period per "
        "revolution, cogging n)",
    frozenset({"cogging", "coulomb_friction"}):
        "slow motion in both directions over the same positions (cogging depends on where the axis is, friction "
        "on which way it moves)",
    frozenset({"cogging", "force_offset"}):
        "motion over more periods of the load (a periodic load averages out over a period, an offset does not)",
    frozenset({"back_emf", "saturation"}):
        "the same large command held at several speeds (back-EMF cuts the drive as the speed rises, a saturation "
        "at any speed)",
    frozenset({"back_emf", "stribeck_friction"}):
        "coasting at several speeds with the command at zero (back-EMF acts only while driven, friction always)",
    frozenset({"gravity_load", "slope"}):
        "motion over a wider range of positions (a gravity load changes with the angle, a slope does not)",
}

GENERIC_EXCITATION = "richer excitation: steps and chirps over the full command range, both directions"


def separating_excitation(a: str, b: str, table: dict[frozenset, str] | None = None) -> str:
    """The excitation that would separate effects ``a`` and ``b`` (``table``: a model's own pairs)."""
    return (LOOK_ALIKES if table is None else table).get(frozenset({a, b}), GENERIC_EXCITATION)


def is_look_alike(a: str, b: str, table: dict[frozenset, str] | None = None) -> bool:
    return frozenset({a, b}) in (LOOK_ALIKES if table is None else table)
