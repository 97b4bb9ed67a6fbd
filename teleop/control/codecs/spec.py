"""A codec spec, parsed once into a typed value: :class:`CodecSpec`.

Why one value: the spec is what a hello carries and what the logs and reports label a run with, so
it must be one canonical string on both sides; and it is what every codec is built from, so its
parameters must be numbers, checked once.  :meth:`CodecSpec.parse` reads the three spellings a user
may type, checks them against :data:`GRAMMARS` and returns the canonical spec, a ``str`` (so the
wire, the logs and every comparison with a spelled-out spec keep working) that also holds its name
and typed parameters; :func:`teleop.control.codecs.make_codec` builds the codec from those
without parsing again.

* positional, as on the wire: ``eds:50``, ``pdr:0.8:100:0.8:30:30:c0.5``;
* named parameters, for a user who does not want to count colons: ``pdr:pct=0.8,bpct=0.8,fr=30,
  br=30,kappa=0.5`` (any order, defaults for the rest);
* a named preset (:data:`PRESETS`): ``low-rate``, ``tdpa``; ``paper`` names a set of codecs, for
  the commands that run several (:func:`expand`).

Only the positional canonical form goes on the wire (PROTOCOL.md 3.5): a peer's hello is parsed with
``local=False``, which refuses presets and named parameters.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from teleop.control.codecs.base import RAW_BITS, CodecError
from teleop.control.codecs.deadband import DEFAULT_HEARTBEAT_MS
from teleop.control.codecs.frequency import MAX_FRAME

MAX_K = 100_000  # ticks (100 s at 1 kHz): any longer frame, horizon or heartbeat is meaningless
MAX_BAND_PCT = 100.0
MAX_RESERVE_PCT = 1000.0  # pdr's FR, BR: the reserve scale of a direction, percent of the default


@dataclass(frozen=True)
class Param:
    """One parameter of a grammar: its name (upper case in the grammar, lower case when named), its
    type and bounds, its default (None: required; ``same`` names the parameter it defaults to)."""

    name: str
    integer: bool
    lo: float
    hi: float
    lo_open: bool = False  # lo excluded (a band of 0 % is no band)
    hi_open: bool = False
    default: float | None = None
    same: str | None = None  # defaults to this other parameter's value (pdr's BPCT: PCT)
    optional: bool = False  # may be absent altogether (cq's RANGE: the session's; pdr's KAPPA: off)
    what: str = ""

    def bounds(self) -> str:
        """``1..100000`` (integers) or ``(0, 100]`` (numbers)."""
        if self.integer:
            return f"{self.lo:g}..{self.hi:g}"
        return ("(" if self.lo_open else "[") + f"{self.lo:g}, {self.hi:g}" + (")" if self.hi_open else "]")


_K = Param("K", True, 1, MAX_K, what="ticks a payload covers")
_PCT = Param("PCT", False, 0.0, MAX_BAND_PCT, lo_open=True, what="deadband in percent")
_MAXMS = Param("MAXMS", True, 1, MAX_K, default=DEFAULT_HEARTBEAT_MS, what="heartbeat, ticks (ms at 1 kHz)")

#: name -> (positional grammar, its parameters in order).  The canonical form of each is the grammar
#: with optional trailing parameters left out when they have their defaults.
GRAMMARS: dict[str, tuple[str, tuple[Param, ...]]] = {
    "none": ("none", ()),
    "ids": ("ids:K", (_K,)),
    "eds": ("eds:K", (_K,)),
    "cq": (
        "cq:BITS[:RANGE]",
        (
            Param("BITS", True, 2, RAW_BITS, what="bits per value"),
            Param(
                "RANGE",
                False,
                0.0,
                math.inf,
                lo_open=True,
                hi_open=True,
                optional=True,
                what="full scale (default the session's)",
            ),
        ),
    ),
    "pd": ("pd:PCT[:MAXMS]", (_PCT, _MAXMS)),
    "pdp": ("pdp:PCT[:MAXMS]", (_PCT, _MAXMS)),
    "pdr": (
        "pdr:PCT[:MAXMS[:BPCT[:FR:BR[:cKAPPA]]]]",
        (
            _PCT,
            _MAXMS,
            Param(
                "BPCT", False, 0.0, MAX_BAND_PCT, lo_open=True, same="PCT", what="backward band (default PCT)"
            ),
            Param("FR", False, 0.0, MAX_RESERVE_PCT, default=100.0, what="forward reserve scale in percent"),
            Param("BR", False, 0.0, MAX_RESERVE_PCT, default=100.0, what="backward reserve scale in percent"),
            Param(
                "KAPPA",
                False,
                0.0,
                100.0,
                hi_open=True,
                optional=True,
                what="self-credit in percent (default off)",
            ),
        ),
    ),
    "dct": (
        "dct:N:M",
        (
            Param("N", True, 2, MAX_FRAME, what="frame, ticks"),
            Param("M", True, 1, MAX_FRAME, what="coefficients, <= N"),
        ),
    ),
}

#: Named presets: one canonical spec each, or a set (``paper``) for the commands that run several.
PRESETS: dict[str, tuple[str, ...]] = {
    # The seed paper's Section V set: no LDR, iDS and eDS at K 2 and 50, CQ at 8 bits.
    "paper": ("none", "ids:2", "ids:50", "eds:2", "eds:50", "cq:8"),
    # The reflective deadband's best low-rate point (frontier0_pool.json, protocol, 15 s, 0 ms):
    # 28.6 / 24.8 packets/s at I = 1.139e-3, below ids:2's 1.158e-3 at 500 / 500.
    "low-rate": ("pdr:0.8:100:0.8:30:30:c0.5",),
    # What the TDPA guide runs with --passivity tdpa: 75 / 55 packets/s at 50 ms one-way.
    "tdpa": ("pdp:5",),
}
PRESET_HELP: dict[str, str] = {
    "paper": f"the seed paper's Section V set, {' '.join(PRESETS['paper'])} (commands that run several)",
    "low-rate": "pdr:0.8:100:0.8:30:30:c0.5, the lowest-rate point at ids:2's transparency",
    "tdpa": "pdp:5, the codec of the TDPA guide (with --passivity tdpa)",
}


def _form_help() -> str:
    forms = " | ".join(g for g, _ in GRAMMARS.values())
    params: dict[str, str] = {}
    for _, ps in GRAMMARS.values():
        for p in ps:
            kind = "integer " if p.integer else ""
            params.setdefault(p.name, f"{p.name} {p.what}, {kind}{p.bounds()}")
    presets = "; ".join(f"{k}: {v}" for k, v in PRESET_HELP.items())
    return (
        f"{forms}  ({'; '.join(params.values())}); or named, NAME:param=VALUE,... in any order "
        f"(e.g. pdr:pct=0.8,bpct=0.8,fr=30,br=30,kappa=0.5); or a preset ({presets})"
    )


#: Every form, each grammar, every parameter and preset: what an error and ``--help`` list.
ACCEPTED = _form_help()


def _number(spec: str, p: Param, text: str) -> float:
    """``text`` as ``p``'s value: an int for an integer parameter, checked against its bounds."""
    try:
        v: float = int(text) if p.integer else float(text)
    except ValueError:
        kind = "an integer" if p.integer else "a number"
        raise CodecError(
            f"codec {spec!r}: {p.name} must be {kind}, got {text!r}; accepted: {ACCEPTED}"
        ) from None
    lo_bad = v <= p.lo if p.lo_open else v < p.lo
    hi_bad = v >= p.hi if p.hi_open else v > p.hi
    if lo_bad or hi_bad or not math.isfinite(v):
        shown = f"{v:g}" if not p.integer else str(v)
        raise CodecError(
            f"codec {spec!r}: {p.name} must be in {p.bounds()}, got {shown}; accepted: {ACCEPTED}"
        )
    return v


class CodecSpec(str):
    """A canonical codec spec (the ``str``: what a hello carries and a log says) with its family
    ``name`` and its parameters ``values`` (by grammar name, defaults filled in; ``RANGE`` and
    ``KAPPA`` absent when not given).  Build one with :meth:`parse`; never mutate it."""

    name: str
    values: dict[str, float]

    def __new__(cls, canonical: str, name: str, values: dict[str, float]) -> CodecSpec:
        self = super().__new__(cls, canonical)
        self.name = name
        self.values = values
        return self

    def __reduce__(self) -> tuple[type, tuple[str, str, dict[str, float]]]:  # pickling (sweep's processes)
        return (CodecSpec, (str(self), self.name, self.values))

    @classmethod
    def parse(cls, text: str | CodecSpec, local: bool = True) -> CodecSpec:
        """``text`` as a canonical spec; :class:`CodecError` says what is wrong and lists every form.

        ``local``: typed by a user, so presets and named parameters are allowed; a peer's hello
        (False) carries the positional form only."""
        if isinstance(text, CodecSpec):
            return text
        if not isinstance(text, str) or not text.strip():
            raise CodecError(f"empty codec spec; accepted: {ACCEPTED}")
        stripped = text.strip()
        preset = PRESETS.get(stripped.lower())
        if preset is not None:
            if not local:
                raise CodecError(f"codec {text!r}: a preset is not a wire spec; send its canonical form")
            if len(preset) != 1:
                raise CodecError(
                    f"codec preset {stripped!r} names {len(preset)} codecs ({' '.join(preset)}); this "
                    "command takes one: pick one of them (teleop sim, sweep and experiment take the set)"
                )
            stripped = preset[0]
        name, values = _read(text, stripped, local)
        canon = _canonical(name, values)
        # The canonical text is what both sides build from: take the values it says (a number
        # beyond %g's 6 digits is rounded there, and both sides must use the same one).
        return cls(canon, name, _read(canon, canon, False)[1])


def _read(spec: str, text: str, local: bool) -> tuple[str, dict[str, float]]:
    name, _, rest = text.partition(":")
    name = name.lower()
    if name not in GRAMMARS:
        raise CodecError(f"unknown codec {name!r} in {spec!r}; accepted: {ACCEPTED}")
    grammar, params = GRAMMARS[name]
    if "=" in rest:
        if not local:
            raise CodecError(
                f"codec {spec!r}: named parameters are not a wire spec; send the positional form"
            )
        return name, _named(spec, name, rest, params)
    fields = rest.split(":") if rest else []
    values: dict[str, float] = {}
    if name == "pdr" and len(fields) == 6:  # the last is cKAPPA
        if fields[5][:1].lower() != "c":
            raise CodecError(
                f"codec {spec!r}: cKAPPA must be c and a number, got {fields[5]!r}; accepted: {ACCEPTED}"
            )
        fields = [*fields[:5], fields[5][1:]]
    allowed = {"pdr": (1, 2, 3, 5, 6)}.get(name) or tuple(
        range(
            sum(1 for p in params if p.default is None and p.same is None and not p.optional), len(params) + 1
        )
    )
    if len(fields) not in allowed:
        takes = f"takes {grammar}" if params else "takes no parameter"
        raise CodecError(
            f"codec {spec!r}: {name!r} {takes}, got {len(fields)} parameter(s); accepted: {ACCEPTED}"
        )
    for p, t in zip(params, fields, strict=False):
        values[p.name] = _number(spec, p, t)
    return name, _defaults(spec, params, values)


def _named(spec: str, name: str, rest: str, params: tuple[Param, ...]) -> dict[str, float]:
    by_name = {p.name.lower(): p for p in params}
    values: dict[str, float] = {}
    for item in rest.split(","):
        key, eq, text = item.partition("=")
        p = by_name.get(key.strip().lower())
        if not eq or p is None:
            names = ", ".join(by_name) or "none"
            raise CodecError(f"codec {spec!r}: {item.strip()!r} is not PARAM=VALUE with PARAM one of {names}")
        if p.name in values:
            raise CodecError(f"codec {spec!r}: {key.strip()} given twice")
        values[p.name] = _number(spec, p, text.strip())
    missing = [
        p.name.lower()
        for p in params
        if p.default is None and p.same is None and not p.optional and p.name not in values
    ]
    if missing:
        raise CodecError(f"codec {spec!r}: {name} needs {', '.join(missing)}; accepted: {ACCEPTED}")
    return _defaults(spec, params, values)


def _defaults(spec: str, params: tuple[Param, ...], values: dict[str, float]) -> dict[str, float]:
    for p in params:
        if p.name not in values:
            if p.same is not None:
                values[p.name] = values[p.same]
            elif p.default is not None:
                values[p.name] = p.default
    if "N" in values and values["M"] > values["N"]:
        raise CodecError(
            f"codec {spec!r}: M must be in 1..{values['N']:g} (N), got {values['M']:g}; accepted: {ACCEPTED}"
        )
    return values


def _g(x: float) -> str:
    """``%g`` without a sign on zero: ``-0`` names the same value as ``0`` and is no canonical form
    (PROTOCOL.md 3.5; issue 49)."""
    return f"{x + 0.0:g}"


def _canonical(name: str, v: dict[str, float]) -> str:
    """The shortest positional form that means the same (PROTOCOL.md 3.5, canonical spec)."""
    if name == "none":
        return "none"
    if name in ("ids", "eds"):
        return f"{name}:{int(v['K'])}"
    if name == "cq":
        return f"cq:{int(v['BITS'])}" + (f":{_g(v['RANGE'])}" if "RANGE" in v else "")
    if name == "dct":
        return f"dct:{int(v['N'])}:{int(v['M'])}"
    pct, hb = _g(v["PCT"]), int(v["MAXMS"])
    if name in ("pd", "pdp"):
        return f"{name}:{pct}" + (f":{hb}" if hb != DEFAULT_HEARTBEAT_MS else "")
    bpct, fr, br = _g(v["BPCT"]), _g(v["FR"]), _g(v["BR"])
    tail = [bpct, fr, br] if (v["FR"], v["BR"]) != (100.0, 100.0) else [bpct]
    if "KAPPA" in v:
        tail = [bpct, fr, br, f"c{_g(100.0 * (v['KAPPA'] / 100.0))}"]
    if tail == [pct]:
        tail = []
    return ":".join(["pdr", pct, *([str(hb)] if tail or hb != DEFAULT_HEARTBEAT_MS else []), *tail])


def expand(text: str) -> list[CodecSpec]:
    """One spec, or every spec a set preset names (``paper``): what a command that runs several
    codecs takes for one ``--codec``."""
    preset = PRESETS.get(text.strip().lower())
    if preset is not None and len(preset) > 1:
        return [CodecSpec.parse(s) for s in preset]
    return [CodecSpec.parse(text)]
