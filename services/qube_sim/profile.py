"""Rig profiles: every physical parameter and non-ideal effect of a simulated QUBE-Servo 2, in one validated model.

A profile is what a family of rigs has in common; each rig draws its own parameters around it from its seed
(``spread``, ``spread_nonideal``), and a rig with domain randomisation draws them again at every episode
(``randomize``, ``ranges``). Built-in profiles: ``ideal`` (the rigs as they were before profiles existed: nominal
plant, no friction, no delays) and ``lab`` (a realistic QUBE-Servo 2; docs/rig-profiles.md gives each value's source
or how it was estimated). ``python -m services.qube_sim --show-profile lab`` prints one as JSON; a file in that form
is accepted wherever a profile name is.
"""

from __future__ import annotations

import json
import random
from dataclasses import replace
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from rpi_bridge.plant import PlantModel
from runtime.rigfiles import RigFileError, folder_files, rig_file
from services.qube_sim.dynamics import QubeParams

#: Profile field -> QubeParams field of the parameters that ``spread`` scales per rig (QubeParams.varied).
PLANT = {"mr": "mr", "Lr": "Lr", "mp": "mp", "Lp": "Lp", "Dr": "Dr", "Dp": "Dp"}
#: ... and of those that ``spread_nonideal`` scales per rig.
NONIDEAL = {"coulomb_arm": "Cr", "static_arm": "Sr", "coulomb_pendulum": "Cp", "static_pendulum": "Sp",
            "deadzone_v": "deadzone", "voltage_offset_v": "voltage_offset", "cable_stiffness": "cable_stiffness",
            "cable_rest_rad": "cable_rest"}
#: The names ``randomize`` and ``ranges`` draw per episode: the above, and "motor" (a factor on km and kt together).
RANDOMIZABLE = (*PLANT, "motor", *NONIDEAL)


class ProfileError(ValueError):
    """A profile that cannot be used: one line saying why."""


def _f(default: float, description: str, ge: float = 0.0, le: float | None = None, gt: float | None = None) -> Any:
    if gt is not None:
        return Field(default, description=description, gt=gt, le=le, allow_inf_nan=False)
    return Field(default, description=description, ge=ge, le=le, allow_inf_nan=False)


class Identified(BaseModel):
    """How a profile was identified from a rig (services/qube_sim/identify.py): the fitted values, each one's 1-sigma
    (relative, a fraction of the value; ``delay_ms``'s in ms), the fit's RMS angle errors and where it came from."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    fitted: dict[str, float] = Field(description="fitted name -> value (profile units; motor: km = kt; delay_ms: "
                                     "a command's delay after its read)")
    sigma: dict[str, float] = Field(description="fitted name -> 1-sigma, relative (delay_ms: in ms)")
    train_rms_deg: float = Field(ge=0, description="RMS angle prediction error on the fitted windows, deg")
    heldout_rms_deg: float = Field(ge=0, description="RMS angle prediction error on the held-out block, deg")
    rig_seconds: float = Field(ge=0, description="rig time of the identification protocol, every attempt's, s")
    attempts: int = Field(1, ge=1, description="recordings made: the last one's fit was trusted, the others' refused")
    fitted_at: str = Field(description="UTC time of the fit (ISO 8601)")
    source: str = Field("", description="the recording it was fitted from")
    base: str = Field("", description="the profile of every value not fitted")
    rig: str = Field("", description="the rig the recording came from")
    fit_wall_s: float = Field(0.0, ge=0, description="wall seconds of the fit")


class RigProfile(BaseModel):
    """A family of simulated rigs (see the module docstring). Units: SI, except volts, milliseconds and counts."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str = Field("custom", description="a label for reports", max_length=64)
    description: str = Field("", description="free text", max_length=2000)
    # -- plant: QUBE-Servo 2 User Manual Table 2.2 ([UM]); damping from gym_brt --------------------------------
    Rm: float = _f(8.4, "motor terminal resistance, ohm", gt=0.5, le=50)
    km: float = _f(0.042, "back-EMF constant, V/(rad/s)", gt=0.005, le=0.5)
    kt: float = _f(0.042, "torque constant, N m/A", gt=0.005, le=0.5)
    mr: float = _f(0.095, "arm mass, kg", gt=0.01, le=1)
    Lr: float = _f(0.085, "arm length, pivot to rod end, m", gt=0.01, le=0.5)
    mp: float = _f(0.024, "pendulum mass, kg", gt=0.002, le=0.5)
    Lp: float = _f(0.129, "pendulum length, m", gt=0.01, le=0.5)
    Dr: float = _f(0.00027, "arm viscous damping, N m s/rad", le=0.05)
    Dp: float = _f(0.00005, "pendulum viscous damping, N m s/rad", le=0.01)
    g: float = _f(9.81, "gravity, m/s^2", gt=9.7, le=9.9)
    # -- friction ----------------------------------------------------------------------------------------------
    coulomb_arm: float = _f(0.0, "arm Coulomb (sliding) friction torque, N m", le=0.05)
    static_arm: float = _f(0.0, "arm static (breakaway) friction torque, N m (0 or >= coulomb_arm)", le=0.05)
    coulomb_pendulum: float = _f(0.0, "pendulum Coulomb friction torque, N m", le=0.01)
    static_pendulum: float = _f(0.0, "pendulum static friction torque, N m (0 or >= coulomb_pendulum)", le=0.01)
    # -- motor and amplifier -----------------------------------------------------------------------------------
    deadzone_v: float = _f(0.0, "motor deadzone, V: no torque below it", le=3)
    voltage_offset_v: float = _f(0.0, "amplifier output offset, V", ge=-1, le=1)
    # -- cable -------------------------------------------------------------------------------------------------
    cable_stiffness: float = _f(0.0, "torque of the encoder cable on the arm per radian from its rest, N m/rad",
                                le=0.02)
    cable_rest_rad: float = _f(0.0, "arm angle at which the cable exerts no torque, rad", ge=-1.6, le=1.6)
    # -- sensing -----------------------------------------------------------------------------------------------
    encoder_noise_counts: float = _f(0.0, "standard deviation of the noise added to each encoder reading, counts "
                                     "(quantisation to 2048 counts/rev is always there)", le=20)
    sensing_latency_ms: float = _f(0.0, "age of the state in each reading, ms", le=7)
    # -- actuation timing on the rig ---------------------------------------------------------------------------
    action_delay_ms: float = _f(0.0, "least delay from a motor write to the motor, ms", le=7)
    action_jitter_ms: float = _f(0.0, "extra delay drawn uniformly from [0, jitter], ms", le=7)
    missed_actions: float = _f(0.0, "fraction of motor writes lost (the motor keeps the previous command)", le=0.5)
    # -- the real loop's timing under the qube_sim clock 'delayed' ---------------------------------------------
    loop_delay_ms: tuple[float, float] = Field((0.0, 7.0), description="clock 'delayed': each action reaches the "
                                               "motor after a delay drawn uniformly from [lo, hi] ms after its "
                                               "state's read")
    loop_miss_rate: float = _f(0.003, "clock 'delayed': fraction of actions lost (the safe action instead)", le=0.5)
    # -- rigs and episodes around the profile ------------------------------------------------------------------
    spread: float = _f(0.05, "each rig scales masses, lengths, damping and motor gain by 1 + N(0, spread), "
                       "clipped to +-3 spread", le=0.3)
    spread_nonideal: float = _f(0.0, "each rig scales friction, deadzone, offset and cable by 1 + N(0, s), clipped "
                                "to [0, 1 + 3 s]", le=1)
    randomize: float = _f(0.0, "domain randomisation: at each reset, draw every randomisable parameter uniformly "
                          "from +-randomize of the profile's value", le=0.5)
    ranges: dict[str, tuple[float, float]] = Field(default_factory=dict, description="domain randomisation: at each "
                                                   "reset, draw these parameters uniformly from [lo, hi] (absolute "
                                                   "values; 'motor' is a factor on km and kt)")
    curriculum: dict[str, int] = Field(default_factory=dict, description="domain randomisation eased in: for a "
                                       "parameter of ranges named here with N, episode e < N draws from [lo, lo + "
                                       "(hi - lo) e / N], the full range from episode N on")
    identified: Identified | None = Field(None, description="set on a profile fitted to a rig's identification "
                                          "recording (docs/how-to/identify.md)")

    @model_validator(mode="after")
    def _consistent(self) -> RigProfile:
        lo, hi = self.loop_delay_ms
        if not 0 <= lo <= hi <= 7:
            raise ValueError(f"loop_delay_ms must satisfy 0 <= lo <= hi <= 7 (the period), got {[lo, hi]}")
        if self.action_delay_ms + self.action_jitter_ms > 7:
            raise ValueError("action_delay_ms + action_jitter_ms must not exceed the 7 ms period")
        for static, coulomb in (("static_arm", "coulomb_arm"), ("static_pendulum", "coulomb_pendulum")):
            if 0 < getattr(self, static) < getattr(self, coulomb):
                raise ValueError(f"{static} must be 0 or at least {coulomb}")
        for key, (a, b) in self.ranges.items():
            if key not in RANDOMIZABLE:
                raise ValueError(f"ranges: unknown parameter {key!r}; randomisable: {', '.join(RANDOMIZABLE)}")
            if not a <= b:
                raise ValueError(f"ranges[{key!r}]: lo {a} must not exceed hi {b}")
        for key, episodes in self.curriculum.items():
            if key not in self.ranges or episodes < 1:
                raise ValueError(f"curriculum[{key!r}]: a parameter of ranges and at least 1 episode, got {episodes}")
        return self

    # -- the plant ---------------------------------------------------------------------------------------------
    def params(self) -> QubeParams:
        """The nominal plant of this profile (no per-rig spread)."""
        return QubeParams(Rm=self.Rm, km=self.km, kt=self.kt, mr=self.mr, Lr=self.Lr, mp=self.mp, Lp=self.Lp,
                          Dr=self.Dr, Dp=self.Dp, g=self.g, Cr=self.coulomb_arm, Cp=self.coulomb_pendulum,
                          Sr=self.static_arm, Sp=self.static_pendulum, deadzone=self.deadzone_v,
                          voltage_offset=self.voltage_offset_v, cable_stiffness=self.cable_stiffness,
                          cable_rest=self.cable_rest_rad)

    def plant_model(self) -> PlantModel:
        """The bridge's model of this profile's nominal rig (rpi_bridge.plant.PlantModel.from_profile of its JSON
        fields): what an identified rig gives the reset and the self-test."""
        return PlantModel.from_profile(self.model_dump())

    def rig_params(self, seed: int) -> QubeParams:
        """Rig ``seed``'s plant: the profile spread by ``spread`` (exactly QubeParams.varied, so ``ideal`` gives the
        rigs of before) and ``spread_nonideal`` (its own random stream). Deterministic in ``seed``."""
        base = self.params()
        p = QubeParams.varied(seed, scale=self.spread, base=base) if self.spread > 0 else base
        if self.spread_nonideal > 0:
            rng = random.Random(f"nonideal-{seed}")
            s = self.spread_nonideal
            p = replace(p, **{name: getattr(p, name) * min(1 + 3 * s, max(0.0, 1 + rng.gauss(0.0, s)))
                              for name in NONIDEAL.values()})
        return p

    def episode_params(self, seed: int, episode: int, randomize: float | None = None,
                       draw: int = 0) -> QubeParams | None:
        """Domain randomisation: the plant of rig ``seed`` for its ``episode``-th reset, every randomisable parameter
        drawn uniformly from +-``randomize`` (default: the profile's) of the profile's value and those in ``ranges``
        from their range, its upper end eased in over the first episodes where ``curriculum`` says (episodes count
        from 1). None when the profile randomises nothing. Deterministic in (seed, episode, draw); ``draw`` > 0 is a
        replacement for a plant that could not be swung up."""
        fraction = self.randomize if randomize is None else randomize
        if fraction <= 0 and not self.ranges:
            return None
        rng = random.Random(f"randomize-{seed}-{episode}" + (f"-{draw}" if draw else ""))
        base = self.params()
        changes: dict[str, float] = {}
        for name in RANDOMIZABLE:
            field = {**PLANT, **NONIDEAL}.get(name)
            nominal = 1.0 if field is None else getattr(base, field)
            lo, hi = self.ranges.get(name, (nominal * (1 - fraction), nominal * (1 + fraction)))
            if episode < (eased := self.curriculum.get(name, 0)):
                hi = lo + (hi - lo) * max(episode, 0) / eased
            value = rng.uniform(lo, hi)
            if field is None:  # motor
                changes.update(km=base.km * value, kt=base.kt * value)
            else:
                changes[field] = value
        return replace(base, **changes)

    # -- sensing and actuation ---------------------------------------------------------------------------------
    def device_options(self) -> dict[str, Any]:
        """Keyword arguments of services.qube_sim.spi_peer.SimulatedQube for this profile's sensing and actuation."""
        return {"sensing_latency_s": self.sensing_latency_ms / 1e3,
                "encoder_noise_counts": self.encoder_noise_counts,
                "action_delay_s": (self.action_delay_ms / 1e3, (self.action_delay_ms + self.action_jitter_ms) / 1e3),
                "missed_actions": self.missed_actions}

    def to_json(self) -> str:
        exclude = {"identified"} if self.identified is None else None  # a profile that was not identified: as before
        return json.dumps(self.model_dump(mode="json", exclude=exclude), indent=2) + "\n"


IDEAL = RigProfile(name="ideal", description="The simulated rigs as they were before profiles: the manual's plant, "
                   "gym_brt's damping, no friction, deadzone, offset, cable, noise or delays on the rig; rigs spread "
                   "by 5 %.")

LAB = RigProfile(
    name="lab",
    description="A realistic QUBE-Servo 2: the manual's plant with dry friction, a motor deadzone and offset, the "
                "encoder cable, sensing and actuation delays and a wider spread between rigs (docs/rig-profiles.md "
                "gives each value's source or estimate).",
    coulomb_arm=0.0015, static_arm=0.002, coulomb_pendulum=0.0001, static_pendulum=0.00015,
    deadzone_v=0.05, voltage_offset_v=0.02,
    cable_stiffness=0.0002, cable_rest_rad=0.05,
    encoder_noise_counts=0.3, sensing_latency_ms=0.5,
    action_delay_ms=0.14, action_jitter_ms=0.5, missed_actions=0.0,
    spread=0.05, spread_nonideal=0.25,
)

BUILTIN: dict[str, RigProfile] = {"ideal": IDEAL, "lab": LAB}


#: ``--rig-model drawn`` (qube-local): the bridge of a simulated rig takes the rig's own plant as its model, and under
#: domain randomisation each drawn plant, as if every rig were identified exactly: a real rig's bridge is given its
#: identified profile (deploy.lab's fine-tune), so a pretrain's resets hand over as the rigs' will.
DRAWN_MODEL = "drawn"


def params_model(p: QubeParams) -> PlantModel:
    """The bridge's model of one simulated plant, as if identified exactly (``--rig-model drawn``)."""
    return PlantModel(Rm=p.Rm, km=p.km, kt=p.kt, mr=p.mr, Lr=p.Lr, mp=p.mp, Lp=p.Lp, Dr=p.Dr, Dp=p.Dp, g=p.g,
                      coulomb_arm=p.Cr, static_arm=p.Sr, deadzone_v=p.deadzone)


def check_model_source(source: str) -> str:
    """A ``--rig-model`` value: ``drawn``, or a profile :func:`load_profile` reads (ProfileError otherwise)."""
    if source != DRAWN_MODEL:
        load_profile(source)
    return source


def load_profile(source: str | Path, seed: int | None = None) -> RigProfile:
    """A built-in profile by name, a JSON file of one, or a folder of them, one per rig: its ``*.json`` files in name
    order, the rig of seed S taking file ``worker_index(S)`` (rig i of a run, whose seed is ``worker_seed(base, i)``:
    protocol/tasks.py). Without ``seed``, every file of a folder is checked and the first returned. ProfileError with
    one clear line otherwise."""
    text = str(source)
    if text in BUILTIN:
        return BUILTIN[text]
    path = Path(text)
    if path.is_dir():
        try:
            profiles = {file: _read_profile(file) for file in folder_files(path)}  # every file checked
            return profiles[rig_file(path, seed)]
        except RigFileError as err:
            raise ProfileError(str(err)) from None
    if not path.is_file():
        raise ProfileError(f"rig profile {text!r} is neither a built-in ({', '.join(BUILTIN)}), a file nor a folder")
    return _read_profile(path)


def _read_profile(path: Path) -> RigProfile:
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ProfileError(f"rig profile {path}: not readable JSON ({exc})") from None
    if not isinstance(data, dict):
        raise ProfileError(f"rig profile {path}: expected a JSON object, got {type(data).__name__}")
    try:
        return RigProfile.model_validate(data)
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(part) for part in first["loc"]) or "profile"
        more = f" (and {exc.error_count() - 1} more)" if exc.error_count() > 1 else ""
        message = "unknown key" if first["type"] == "extra_forbidden" else first["msg"]
        raise ProfileError(f"rig profile {path}: {where}: {message}{more}") from None
