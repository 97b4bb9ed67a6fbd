"""One session's channel settings, and the one place each of their defaults is set.

A session's settings have three users: the command line, ``teleop sim``
(:class:`teleop.offline.sim.SimConfig`) and the handshake (:class:`teleop.session.protocol.SessionParams`,
what both processes agree on); the ports get theirs from either through
:meth:`teleop.session.node.PortOptions.of`.  All of them are :class:`Channel`:
the fields below are declared here once, with their defaults, and checked here once
(:meth:`Channel.checked`), so a real session and its simulation cannot disagree on what an option
left out means.  What a *missing* optional field of a hello means is the protocol's business, not
a default: see :data:`teleop.session.protocol.WIRE_ABSENT`.

The model's settings (scenario, DoF, b, range, duration) default to the scenario's
(:mod:`teleop.devices.scenarios`); the codec to the command's.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from enum import StrEnum
from typing import Any, Protocol

from teleop import limits
from teleop.control.codecs import make_codec
from teleop.control.codecs.spec import CodecSpec
from teleop.control.passivity import DEFAULT_LINK_TIMEOUT, ON_LOSS
from teleop.control.ratecap import RateCap
from teleop.session.link.netem import NetemError, make_link, parse_netem
from teleop.session.playout import MAX_EXTRA_MS, parse_playout
from teleop.session.wire import max_session_datagram_bytes

#: The most a robot may be told to hold in its outgoing shim: packets (the wire's u32 limit is
#: what a spec may say; a robot's flag is bounded here) and ms.
MAX_BACKWARD_QUEUE = 1_000_000
MAX_BACKWARD_HOLD_MS = 3_600_000.0
#: The longest a robot may be told to act alone (ms): the longest silence and playout, plus a fade.
MAX_ACT_ALONE_MS = 3_600_000.0


#: The node's link supervision (``teleop.session.node``: ``SPARSE_MARGIN_S``, ``PortOptions.fade_time``),
#: restated here for the robot's cap on how long it acts alone (tests/test_welcome.py checks both
#: against the node): how late the payload after a lost one may be, and the fade's length.
SPARSE_MARGIN_S = 0.010
FADE_S = 0.1
#: The shortest fade a robot shortens its own to (s): below it the proposal is refused.  Why not
#: shorter: with a 30 ms fade pd:5's held payloads played more energy than was reported (the
#: conformance suite's deadband rule failed, 491 ticks by 2e-6 J); at 90 ms it passes.
MIN_FADE_S = 0.08


def silence_allowed_s(k: int, dt: float, link_timeout: float) -> float:
    """The silence after a payload a node allows before its link is lost (PROTOCOL.md 5.3): the
    payload interval ``k dt`` plus the link timeout, or for a sparse codec one lost payload more."""
    interval = k * dt
    return interval + (max(link_timeout, interval + SPARSE_MARGIN_S) if k > 1 else link_timeout)


def playout_extra_s(playout: str, dt: float) -> float:
    """The fixed allowance a playout buffer adds (``teleop.session.playout``): a number of ms
    rounded up to ticks; ``off`` and ``auto`` none (auto's is capped by the robot at run time)."""
    if playout in ("off", "auto"):
        return 0.0
    return math.ceil(float(playout) * 1e-3 / dt - 1e-9) * dt


@dataclass(frozen=True)
class Acting:
    """The longest a robot acts after its operator's last packet arrives, by part (s): the playout
    buffer holds it ``playout``, the link is lost ``silence`` after it is played, and the coupling
    fades to 0 over ``fade`` (shortened by the robot to fit its cap, never below ``MIN_FADE_S``)."""

    playout: float
    silence: float
    fade: float

    @property
    def total(self) -> float:
        return self.playout + self.silence + self.fade


def acting_alone(p: Proposal, cap_s: float) -> Acting:
    """How long a robot whose cap is ``cap_s`` acts after the last packet of a session of ``p``:
    ``playout + silence + fade``, the fade shortened (from ``FADE_S``) to fit the cap."""
    k = make_codec(CodecSpec.parse(p.codec), p.dof).k  # the payload interval (no range in it)
    playout = playout_extra_s(p.playout, p.dt)
    silence = silence_allowed_s(k, p.dt, p.link_timeout)
    return Acting(playout, silence, min(FADE_S, cap_s - playout - silence))


class Passivity(StrEnum):
    """The two architectures: scattering waves (eq. 3-5) or TDPA on power variables
    (``teleop.control.passivity``).  A ``str``: what a hello carries and a report says."""

    WAVE = "wave"
    TDPA = "tdpa"

    @classmethod
    def of(cls, text: str) -> Passivity:
        """``text`` as an architecture; ValueError says what is allowed."""
        try:
            return cls(text)
        except ValueError:
            raise ValueError(f"passivity must be one of {', '.join(PASSIVITY)}, got {text!r}") from None


PASSIVITY = tuple(p.value for p in Passivity)
#: The codec of a settings object that names none: no LDR (parsed once, here).
NO_CODEC = CodecSpec.parse("none")
#: What an operator proposes when not told (``teleop operator`` and ``teleop run``): the codec that
#: cuts 98% of the packets at the paper's protocol, and the paper's Section VI task.
DEFAULT_CODEC = "eds:50"
DEFAULT_SCENARIO = "protocol"


@dataclass(frozen=True, kw_only=True)
class Channel:
    """How the channel between the two ports behaves: impairment, reconstruction, passivity.

    Text fields hold the canonical spelling, which is also what a hello carries; :meth:`checked`
    parses each once and says what is wrong.  The codec is parsed on construction, into a
    :class:`teleop.control.codecs.CodecSpec` (a ``str``: its canonical spelling; :attr:`codec_spec` gives
    it typed), and ``passivity`` into :class:`Passivity`; both are passed on, never parsed again."""

    codec: str = NO_CODEC  # LDR codec spec (teleop.control.codecs; presets and named parameters resolved)

    netem_forward: str = ""  # impairment of operator -> TO (applied by the operator's shim)
    netem_backward: str = ""  # impairment of TO -> operator (applied by the TO's shim)
    seed: int = 0  # link seeds: 2 seed forward, 2 seed + 1 backward (a spec's own ``seed N`` wins)
    on_loss: str = "conceal"  # receivers' reconstruction when nothing is queued (teleop.control.passivity)
    controller: bool = True  # passivity controller on both receivers
    link_timeout: float = DEFAULT_LINK_TIMEOUT  # s of silence before a side goes to its safe state
    rate_cap: float = 0.0  # bit/s per direction in any 100 ms window (teleop.control.ratecap); 0: none
    playout: str = "auto"  # receivers' playout buffer: off, auto or extra ms (teleop.session.playout)
    variation: float = 0.0  # scale of the human's seeded variation (devices.models.ProtocolPlan); 0: none
    passivity: Passivity = Passivity.WAVE  # scattering waves (eq. 3-5) or TDPA on power variables

    def __post_init__(self) -> None:
        # CodecSpec.parse and Passivity.of return a value that is parsed already as it is: a copy
        # (dataclasses.replace) or a settings type built from another parses nothing again.
        object.__setattr__(self, "codec", CodecSpec.parse(self.codec))
        object.__setattr__(self, "passivity", Passivity.of(self.passivity))

    @property
    def codec_spec(self) -> CodecSpec:
        """The codec spec, typed (parsed on construction)."""
        assert isinstance(self.codec, CodecSpec)
        return self.codec

    @property
    def tdpa(self) -> bool:
        """Power variables and TDPA rather than waves."""
        return self.passivity == Passivity.TDPA

    def check_channel(self, *, netem_files: bool) -> str:
        """Check every channel field; return the canonical playout (ValueError says what is wrong).

        ``netem_files``: a ``trace FILE`` spec is loaded to check it (settings typed locally); a
        peer's settings never open a file (:meth:`teleop.session.protocol.SessionParams.from_msg` checks
        their specs without it)."""
        if self.on_loss not in ON_LOSS:
            raise ValueError(f"on_loss must be one of {', '.join(ON_LOSS)}, got {self.on_loss!r}")
        if not self.link_timeout > 0:
            raise ValueError(f"link_timeout must be > 0 s, got {self.link_timeout!r}")
        if self.rate_cap:
            RateCap(self.rate_cap, 1e-3)  # ValueError saying the allowed range
        if netem_files:
            for name in ("netem_forward", "netem_backward"):
                text = getattr(self, name)
                if not text.strip():
                    continue
                try:
                    make_link(text, self.seed)  # NetemError (a ValueError) names the bad token
                except NetemError as e:  # a trace file refused (teleop.files): say for which direction
                    if text.split()[:1] == ["trace"]:
                        raise ValueError(f"{name}: {e}") from None
                    raise
        return parse_playout(self.playout)

    def channel_fields(self) -> dict[str, Any]:
        """This object's :class:`Channel` fields, to build another settings type from them."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(Channel)}

    @classmethod
    def fields_from(cls, m: Mapping[str, Any]) -> dict[str, Any]:
        """The :class:`Channel` fields present in ``m`` (the rest keep their defaults)."""
        return {f.name: m[f.name] for f in dataclasses.fields(Channel) if f.name in m}


#: Every default in one object: ``DEFAULTS.playout`` is what a left-out ``--playout`` means.
DEFAULTS = Channel()


# --- the robot's envelope ------------------------------------------------------------------------


def _num(x: float) -> str:
    """A number as a reject reason says it: ``0.25``, ``1e+06``, and every digit it needs beyond
    ``%g``'s six (``2.0000001``): a value above a limit never reads as equal to it (issue 49:
    "range 2 exceeds this robot's limit 2")."""
    if isinstance(x, int):
        return str(x)
    short = f"{x:g}"
    return short if float(short) == x else repr(float(x))


def _ms(seconds: float) -> str:
    """A duration in seconds said in ms: the float noise of the conversion and of sums
    (``410.00000000000006``) rounded off at 1e-9 ms, far below what any limit here tells apart."""
    return _num(round(seconds * 1e3, 9))


class Proposal(Protocol):
    """What :meth:`Envelope.check` reads of a proposed session (``teleop.session.protocol.SessionParams``)."""

    @property
    def codec(self) -> str: ...
    @property
    def dof(self) -> int: ...
    @property
    def b(self) -> float: ...
    @property
    def full_scale(self) -> float: ...
    @property
    def dt(self) -> float: ...
    @property
    def on_loss(self) -> str: ...
    @property
    def controller(self) -> bool: ...
    @property
    def link_timeout(self) -> float: ...
    @property
    def playout(self) -> str: ...
    @property
    def passivity(self) -> Passivity: ...
    @property
    def netem_backward(self) -> str: ...


@dataclass(frozen=True)
class Envelope:
    """The robot's own limits: what it affords whatever a key-holding operator proposes.

    A key proves who the operator is, not that its settings are safe: every setting an
    operator proposes is held to one of these by the rule :data:`SETTINGS` gives it, and a proposal
    outside them is refused with a reject naming the field and the limit.  The robot also saturates
    what it is commanded to ``max_velocity`` and ``max_force`` per DoF (``teleop.session.node``: saturation
    only removes energy), and its energy guard is bounded by these numbers, never the operator's.
    The defaults are the built-in scenarios' own (range 2, b 1 to 20) with room for their peaks
    (1.0 m/s and 7 N measured in every Section V and VI run)."""

    max_range: float = 2.0  # sqrt(W): the largest wave range of any codec the robot plays (CQ's RANGE too)
    min_b: float = 1.0  # N s/m: a low impedance turns a small wave into a fast motion (v = sqrt(2/b) g)
    max_b: float = 20.0  # N s/m: a high one into a large force (F = sqrt(2 b) g)
    max_dof: int = limits.MAX_DOF  # the robot device's own (teleop.devices.max_dof)
    dt: float = 0.001  # s: the robot's own period; a session runs at it or not at all
    passivity: tuple[Passivity, ...] = tuple(Passivity)  # the architectures this robot runs
    on_loss: tuple[str, ...] = ON_LOSS  # the reconstructions it plays on a loss
    # The reconstructions it plays with the passivity controller off: none (the default) refuses the
    # controller off; a robot that allows it names which (zero is passive; hold and conceal are not).
    uncontrolled_on_loss: tuple[str, ...] = ()
    max_link_timeout: float = 0.25  # s: the longest it keeps acting on a silent link
    max_playout_ms: float = 200.0  # ms: the largest fixed playout delay it adds
    max_velocity: float = 1.5  # m/s per DoF: what it is ever commanded
    max_force: float = 50.0  # N per DoF: the contact force it pushes to at most
    # The robot's own outgoing shim (the backward netem an operator proposes) is the robot's memory
    # and time: it holds at most this many packets (the spec's ``limit``; netem's default) ...
    max_backward_queue: int = 1000
    # ... and none longer than this (delay, the jitter's widest draw, a rate's full queue).
    max_backward_hold_ms: float = 1000.0
    # ms: the longest it acts after its operator's last packet arrives (playout + silence + fade:
    # :func:`acting_alone`); it shortens its fade to fit, and refuses what no fade fits.
    max_act_alone_ms: float = 300.0

    def __post_init__(self) -> None:
        for name in ("max_range", "min_b", "max_b", "max_link_timeout", "max_velocity", "max_force", "dt"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a finite number > 0, got {v!r}")
        if self.min_b > self.max_b:
            raise ValueError(f"min_b {_num(self.min_b)} must not exceed max_b {_num(self.max_b)}")
        queue, hold = self.max_backward_queue, self.max_backward_hold_ms
        if not (type(queue) is int and 1 <= queue <= MAX_BACKWARD_QUEUE):
            raise ValueError(f"max_backward_queue must be an integer 1..{MAX_BACKWARD_QUEUE}, got {queue!r}")
        if not 0 <= hold <= MAX_BACKWARD_HOLD_MS:
            raise ValueError(f"max_backward_hold_ms must be 0..{_num(MAX_BACKWARD_HOLD_MS)}, got {hold!r}")
        if not MIN_FADE_S * 1e3 <= self.max_act_alone_ms <= MAX_ACT_ALONE_MS:
            raise ValueError(
                f"max_act_alone_ms must be {_ms(MIN_FADE_S)}..{_num(MAX_ACT_ALONE_MS)}, "
                f"got {self.max_act_alone_ms!r}"
            )
        if not 0 <= self.max_playout_ms <= MAX_EXTRA_MS:
            raise ValueError(f"max_playout_ms must be 0..{_num(MAX_EXTRA_MS)}, got {self.max_playout_ms!r}")
        if not set(self.passivity) <= set(PASSIVITY) or not self.passivity:
            raise ValueError(f"passivity must be some of {', '.join(PASSIVITY)}, got {self.passivity!r}")
        object.__setattr__(self, "passivity", tuple(Passivity.of(p) for p in self.passivity))
        if not set(self.on_loss) <= set(ON_LOSS) or not self.on_loss:
            raise ValueError(f"on_loss must be some of {', '.join(ON_LOSS)}, got {self.on_loss!r}")
        if not set(self.uncontrolled_on_loss) <= set(ON_LOSS):
            raise ValueError(
                f"uncontrolled_on_loss must be some of {', '.join(ON_LOSS)}, "
                f"got {self.uncontrolled_on_loss!r}"
            )

    def check(self, p: Proposal) -> str | None:
        """The first proposed setting outside this envelope, said as a reject reason (the field,
        what was proposed, the limit and the robot's flag that sets it), or None.  Each field's
        rule is the one :data:`SETTINGS` documents."""
        for field_name, got, lo, hi, unit in (
            ("range", p.full_scale, None, self.max_range, ""),
            ("b", p.b, self.min_b, self.max_b, " N s/m"),
            ("dof", p.dof, None, self.max_dof, ""),
            ("link_timeout", p.link_timeout, None, self.max_link_timeout, " s"),
        ):
            flags = ROBOT_FLAGS[field_name]
            if hi is not None and got > hi:
                limit = f"this robot's limit {_num(hi)}{unit} ({flags[-1]})"
                return f"{field_name} {_num(got)}{unit} exceeds {limit}"
            if lo is not None and got < lo:
                limit = f"this robot's limit {_num(lo)}{unit} ({flags[0]})"
                return f"{field_name} {_num(got)}{unit} is below {limit}"
        if p.dt != self.dt:
            return f"dt {_num(p.dt)} is not this robot's period {_num(self.dt)} s (a session runs at it)"
        if p.passivity not in self.passivity:
            return (
                f"passivity {p.passivity} is not allowed by this robot, which runs "
                f"{', '.join(self.passivity)} (--allow-passivity)"
            )
        if not p.controller and not self.uncontrolled_on_loss:
            return "controller off is not allowed by this robot (--allow-no-controller)"
        allowed = self.on_loss if p.controller else self.uncontrolled_on_loss
        if p.on_loss not in allowed:
            if p.controller:
                return (
                    f"on_loss {p.on_loss} is not allowed by this robot; it allows "
                    f"{', '.join(allowed)} (--allow-on-loss)"
                )
            return (
                f"on_loss {p.on_loss} is not allowed by this robot without the passivity controller; "
                f"it allows {', '.join(allowed)} there (--allow-no-controller)"
            )
        if p.playout not in ("off", "auto") and float(p.playout) > self.max_playout_ms:
            return (
                f"playout {p.playout} ms exceeds this robot's limit {_num(self.max_playout_ms)} ms "
                "(--max-playout)"
            )
        return self._check_codec(p) or self._check_backward(p) or self._check_acting(p)

    def _check_acting(self, p: Proposal) -> str | None:
        """The longest the robot acts after its operator's last packet, within ``max_act_alone_ms``
        with a fade of at least ``MIN_FADE_S`` (it shortens its own fade to fit)."""
        try:
            a = acting_alone(p, self.max_act_alone_ms * 1e-3)
        except ValueError:
            return None  # a codec that does not parse: the hello's parser says what is wrong
        if a.fade >= MIN_FADE_S - 1e-12:
            return None
        need = a.playout + a.silence + MIN_FADE_S
        return (
            f"link_timeout {_ms(p.link_timeout)} ms with codec {p.codec} and playout {p.playout}: "
            f"this robot would act {_ms(need)} ms after its operator's last packet (playout "
            f"{_ms(a.playout)} + silence {_ms(a.silence)} + fade {_ms(MIN_FADE_S)} "
            f"at least), beyond its limit {_num(self.max_act_alone_ms)} ms (--max-act-alone)"
        )

    def _check_backward(self, p: Proposal) -> str | None:
        """The operator's backward impairment runs in this robot's shim: its queue (memory: at most
        ``max_backward_queue`` datagrams of the session) and how long it holds a packet are capped.
        A ``trace FILE`` reaches here only if the robot named it (its own choice)."""
        text = p.netem_backward
        if not text.strip() or text.split()[0] == "trace":
            return None
        try:
            spec = parse_netem(text)
        except NetemError:
            return None  # (the hello's parser says what is wrong)
        if spec.limit > self.max_backward_queue:
            return (
                f"netem_backward limit {spec.limit} exceeds this robot's limit {self.max_backward_queue} "
                "packets (--max-backward-queue)"
            )
        hold_ms = spec.longest_hold(max_session_datagram_bytes(p.dof)) * 1e3
        if hold_ms > self.max_backward_hold_ms:
            return (
                f"netem_backward holds a packet up to {_num(hold_ms)} ms, beyond this robot's limit "
                f"{_num(self.max_backward_hold_ms)} ms (--max-backward-hold)"
            )
        return None

    def _check_codec(self, p: Proposal) -> str | None:
        """Every wave range the proposed codec would play (CQ's RANGE included) within
        ``max_range``: the range bounds the power the robot may be commanded with
        (P <= b range^2 / 2 per DoF in waves; TDPA's power ranges follow from it and b)."""
        needed = codec_range(p)
        if needed > self.max_range * (1 + 1e-12):
            return (
                f"codec {p.codec} plays a wave range of {_num(needed)}, beyond this robot's limit "
                f"{_num(self.max_range)} (--max-range)"
            )
        return None

    def owning_backward(self, spec: str | None) -> Envelope:
        """This envelope admitting the robot's own pinned backward impairment ``spec`` (the robot's
        choice, at any DoF): a robot is never refused its own setting."""
        if not spec or not spec.strip() or spec.split()[0] == "trace":
            return self
        ns = parse_netem(spec)
        hold_ms = min(ns.longest_hold(max_session_datagram_bytes(self.max_dof)) * 1e3, MAX_BACKWARD_HOLD_MS)
        return dataclasses.replace(
            self,
            max_backward_queue=max(self.max_backward_queue, min(ns.limit, MAX_BACKWARD_QUEUE)),
            max_backward_hold_ms=max(self.max_backward_hold_ms, hold_ms),
        )

    def admitting(self, p: Proposal) -> Envelope:
        """This envelope widened just enough to admit ``p``: the robot of a user who chose ``p``
        for both sides (``teleop run``'s teleoperator, ``teleop sim``'s robot), and nothing more."""
        fixed = p.playout not in ("off", "auto")
        return dataclasses.replace(
            self,
            max_range=max(self.max_range, p.full_scale, codec_range(p)),
            min_b=min(self.min_b, p.b),
            max_b=max(self.max_b, p.b),
            max_dof=max(self.max_dof, p.dof),
            dt=p.dt,
            passivity=tuple(dict.fromkeys((*self.passivity, p.passivity))),
            on_loss=tuple(dict.fromkeys((*self.on_loss, p.on_loss))),
            uncontrolled_on_loss=self.uncontrolled_on_loss
            if p.controller
            else tuple(dict.fromkeys((*self.uncontrolled_on_loss, p.on_loss))),
            max_link_timeout=max(self.max_link_timeout, p.link_timeout),
            max_playout_ms=max(self.max_playout_ms, float(p.playout) if fixed else 0.0),
            max_act_alone_ms=max(self.max_act_alone_ms, _full_acting_ms(p)),
            **_backward_admitting(self, p),
        )


def _full_acting_ms(p: Proposal) -> float:
    """What ``p`` needs of a robot's ``max_act_alone_ms`` to keep its full fade (``FADE_S``)."""
    try:
        a = acting_alone(p, math.inf)
    except ValueError:
        return 0.0
    return min((a.playout + a.silence + FADE_S) * 1e3, MAX_ACT_ALONE_MS)


def _backward_admitting(env: Envelope, p: Proposal) -> dict[str, Any]:
    """:meth:`Envelope.admitting`'s backward shim limits: widened to ``p``'s backward spec."""
    text = p.netem_backward
    if not text.strip() or text.split()[0] == "trace":
        return {}
    spec = parse_netem(text)
    hold_ms = spec.longest_hold(max_session_datagram_bytes(p.dof)) * 1e3
    return {
        "max_backward_queue": max(env.max_backward_queue, min(spec.limit, MAX_BACKWARD_QUEUE)),
        "max_backward_hold_ms": max(env.max_backward_hold_ms, min(hold_ms, MAX_BACKWARD_HOLD_MS)),
    }


def codec_range(p: Proposal) -> float:
    """The largest wave range (sqrt(W)) the proposed codec plays: the session's range, or CQ's own
    RANGE; under TDPA the wave range its power ranges (``teleop.session.port.power_ranges``) stand for.
    0 for a codec spec that does not parse (the handshake's own checks say what is wrong)."""
    from teleop.control.codecs import CodecError

    tdpa = p.passivity == Passivity.TDPA
    # (the range the port gives the codec, what one unit of wave range is in that range)
    ranges = (
        [
            (p.full_scale * math.sqrt(2.0 / p.b), math.sqrt(2.0 / p.b)),
            (p.full_scale * math.sqrt(2.0 * p.b), math.sqrt(2.0 * p.b)),
        ]
        if tdpa
        else [(p.full_scale, 1.0)]
    )
    needed = 0.0
    for session_range, unit in ranges:
        try:
            c = make_codec(CodecSpec.parse(p.codec), p.dof, session_range, power=tdpa)  # a spec: no parsing
        except CodecError:
            return 0.0
        needed = max(needed, c.raw.full_scale / unit)
    return needed


DEFAULT_ENVELOPE = Envelope()


# --- the settings table --------------------------------------------------------------------------


@dataclass(frozen=True)
class Setting:
    """One session setting: where it is typed, what it is called in a hello, and the robot's rule."""

    field: str  # the attribute of SessionParams (and SimConfig)
    key: str  # its key in a hello's parameters (PROTOCOL.md 4.2)
    default: str | None  # what it is when no one says; None: a channel field's, read from DEFAULTS
    proposable: bool  # may the operator propose it?
    rule: str  # the robot's rule: pin, cap, floor, allowed set, or its own
    flag: str | None  # the operator's command-line flag (None: not typed)
    robot_flags: tuple[str, ...] = ()  # the robot's flags that set its rule


#: Every setting of a session, once: the hello's keys (``SessionParams.to_msg``), the robot's rules
#: (:class:`Envelope`, ``teleop.session.protocol.Pins``), its command-line flags and the docs' table
#: (``tools/docgen.py``) are all read from here.
SETTINGS: tuple[Setting, ...] = (
    Setting("session", "session", "random", True, "the operator's: a fresh id per session", "--session"),
    Setting(
        "codec",
        "codec",
        DEFAULT_CODEC,
        True,
        "pinned by --codec; every range it plays (CQ's RANGE included) capped by --max-range",
        "--codec",
        ("--codec", "--max-range"),
    ),
    Setting(
        "scenario", "scenario", DEFAULT_SCENARIO, True, "pinned by --scenario", "--scenario", ("--scenario",)
    ),
    Setting(
        "dof",
        "dof",
        "the scenario's",
        True,
        "pinned by --dof; the robot device's own DoF",
        "--dof",
        ("--dof",),
    ),
    Setting(
        "b",
        "b",
        "the scenario's",
        True,
        f"pinned by --b; within --min-b and --max-b (default {_num(DEFAULT_ENVELOPE.min_b)} to "
        f"{_num(DEFAULT_ENVELOPE.max_b)} N s/m)",
        "--b",
        ("--b", "--min-b", "--max-b"),
    ),
    Setting(
        "full_scale",
        "range",
        "the scenario's",
        True,
        f"pinned by --range; capped by --max-range (default {_num(DEFAULT_ENVELOPE.max_range)})",
        "--range",
        ("--range", "--max-range"),
    ),
    Setting(
        "duration", "duration", "the scenario's", True, "pinned by --duration", "--duration", ("--duration",)
    ),
    Setting("dt", "dt", "0.001 s", False, "the robot's own period: anything else is refused", None),
    Setting("phase", "phase", "0.5", True, "caps the robot's first phase; held in [0.25, 0.9]", "--phase"),
    Setting(
        "netem_forward",
        "netem_forward",
        None,
        True,
        "pinned by --netem/--netem-forward; a trace FILE only if the robot named it",
        "--netem-forward",
        ("--netem", "--netem-forward"),
    ),
    Setting(
        "netem_backward",
        "netem_backward",
        None,
        True,
        "pinned by --netem/--netem-backward; else its queue capped by --max-backward-queue (default "
        f"{DEFAULT_ENVELOPE.max_backward_queue} packets: memory at most that many of the session's "
        "datagrams) and its longest hold (delay, widest jitter, a rate's full queue) by "
        f"--max-backward-hold (default {_num(DEFAULT_ENVELOPE.max_backward_hold_ms)} ms); "
        "a trace FILE only if the robot named it",
        "--netem-backward",
        ("--netem", "--netem-backward", "--max-backward-queue", "--max-backward-hold"),
    ),
    Setting("seed", "seed", None, True, "the operator's (seeds the shims and the human)", "--seed"),
    Setting(
        "on_loss",
        "on_loss",
        None,
        True,
        "one of --allow-on-loss (default all); without the controller one of --allow-no-controller's",
        "--on-loss",
        ("--allow-on-loss",),
    ),
    Setting(
        "controller",
        "controller",
        None,
        True,
        "refused off unless the robot says --allow-no-controller [LIST] (default zero)",
        "--no-controller",
        ("--allow-no-controller",),
    ),
    Setting(
        "link_timeout",
        "link_timeout",
        None,
        True,
        f"capped by --max-link-timeout (default {_ms(DEFAULT_ENVELOPE.max_link_timeout)} ms); "
        "with the codec's payload interval, the playout and the fade, by --max-act-alone (default "
        f"{_num(DEFAULT_ENVELOPE.max_act_alone_ms)} ms: the longest the robot acts after its "
        "operator's last packet; it shortens its fade, down to "
        f"{_ms(MIN_FADE_S)} ms, to fit)",
        "--link-timeout",
        ("--max-link-timeout", "--max-act-alone"),
    ),
    Setting(
        "rate_cap",
        "rate_cap",
        None,
        True,
        "pinned by --rate-cap (a cap only holds payloads back: it removes energy, never adds)",
        "--rate-cap",
        ("--rate-cap",),
    ),
    Setting(
        "playout",
        "playout",
        None,
        True,
        f"a fixed delay capped by --max-playout (default {_num(DEFAULT_ENVELOPE.max_playout_ms)} ms) "
        "and, with the link timeout, by --max-act-alone; auto's allowance capped at what "
        "--max-act-alone leaves",
        "--playout",
        ("--max-playout", "--max-act-alone"),
    ),
    Setting("variation", "variation", None, True, "the operator's (the human's variation)", "--variation"),
    Setting(
        "passivity",
        "passivity",
        None,
        True,
        "one of --allow-passivity (default wave,tdpa)",
        "--passivity",
        ("--allow-passivity",),
    ),
)

#: The robot's flags of each envelope check, by the field name a reject reason says.
ROBOT_FLAGS: dict[str, tuple[str, ...]] = {
    "range": ("--max-range",),
    "b": ("--min-b", "--max-b"),
    "dof": ("--robot",),
    "link_timeout": ("--max-link-timeout",),
}


def _default_text(s: Setting) -> str:
    """A setting's default as the docs' table says it: a channel field's is read from DEFAULTS."""
    if s.default is not None:
        return s.default
    v = getattr(DEFAULTS, s.field)
    if s.field == "link_timeout":
        return f"{_ms(v)} ms"
    if s.field == "on_loss":
        return f"{v} (zero without the controller)"
    if isinstance(v, bool):
        return "on" if v else "off"
    if v in ("", 0.0):
        return "none" if s.field in ("netem_forward", "netem_backward", "rate_cap") else str(v)
    return str(v)


def settings_table() -> str:
    """The docs' table of :data:`SETTINGS` (Markdown), generated: nothing about it is typed twice."""
    rows = [
        "| setting | hello key | default | operator proposes | robot's rule | operator flag |",
        "|---|---|---|---|---|---|",
    ]
    for s in SETTINGS:
        rows.append(
            f"| {s.field} | `{s.key}` | {_default_text(s)} | {'yes' if s.proposable else 'no'} | {s.rule} | "
            f"{f'`{s.flag}`' if s.flag else '-'} |"
        )
    return "\n".join(rows) + "\n"
