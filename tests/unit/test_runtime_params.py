"""Parameters: declared defaults and units, coercion, refusals that keep the old value, live sets,
start-only parameters, parameter files and command-line overrides."""
from __future__ import annotations

import math

import pytest


from aeroperception.services.runtime import (
    Param, ParamError, ParamSet,
)
from aeroperception.services.runtime.params import parse_overrides, start_only_but


DECL = [
    Param("max_velocity_mps", 2.0, "m/s", 0.1, 15.0, description="cruise speed"),
    Param("retries", 3, "", 0, 10),
    Param("enabled", True),
    Param("mode", "fast", choices=("fast", "safe")),
    Param("label", "x"),
]


def params() -> ParamSet:
    return ParamSet.from_declarations(DECL)


def test_params_declared_defaults_units_and_access():
    ps = params()
    assert ps.values == {"max_velocity_mps": 2.0, "retries": 3, "enabled": True, "mode": "fast", "label": "x"}
    assert ps["retries"] == 3 and ps.max_velocity_mps == 2.0
    p = ps.declared["max_velocity_mps"]
    assert (p.type, p.unit, p.min, p.max, p.description) == (float, "m/s", 0.1, 15.0, "cruise speed")
    with pytest.raises(AttributeError):
        ps.not_a_param  # noqa: B018


@pytest.mark.parametrize("name,given,expected", [
    ("max_velocity_mps", "1.5", 1.5),     # CLI strings are parsed
    ("max_velocity_mps", 3, 3.0),         # int -> float
    ("retries", "4", 4),
    ("retries", 5.0, 5),                  # integral float -> int
    ("enabled", "false", False),
    ("enabled", "true", True),
    ("mode", "safe", "safe"),
    ("label", "123", "123"),              # a str parameter keeps strings as strings
])
def test_params_type_coercion(name, given, expected):
    ps = params()
    assert ps.set(name, given) == expected
    assert ps[name] == expected and type(ps[name]) is type(expected)


@pytest.mark.parametrize("name,bad,words", [
    ("max_velocity_mps", "fast", "finite number"),
    ("max_velocity_mps", float("nan"), "finite number"),
    ("max_velocity_mps", math.inf, "finite number"),
    ("max_velocity_mps", True, "finite number"),
    ("max_velocity_mps", 0.01, "below the minimum 0.1 m/s"),
    ("max_velocity_mps", 20, "above the maximum 15.0 m/s"),
    ("retries", 2.5, "integer"),
    ("retries", True, "integer"),
    ("retries", -1, "below the minimum"),
    ("enabled", 1, "true/false"),
    ("enabled", "1", "true/false"),
    ("mode", "reckless", "not one of ['fast', 'safe']"),
    ("label", 5, "string"),
    ("nope", 1, "unknown parameter 'nope'"),
])
def test_params_invalid_values_rejected_and_old_value_kept(name, bad, words):
    ps = params()
    before = dict(ps.values)
    with pytest.raises(ParamError) as e:
        ps.set(name, bad)
    assert words in str(e.value)
    assert ps.values == before


def test_params_update_is_atomic_and_notifies():
    ps = params()
    seen = []
    ps.on_change(lambda n, v: seen.append((n, v)))
    with pytest.raises(ParamError):
        ps.update({"retries": 5, "max_velocity_mps": 99})
    assert ps["retries"] == 3 and seen == []
    ps.update({"retries": 5, "mode": "safe"})
    assert ps["retries"] == 5 and ps["mode"] == "safe"
    assert sorted(seen) == [("mode", "safe"), ("retries", 5)]


def test_params_live_set_refused_by_apply_callback_keeps_what_runs():
    """An apply callback that refuses a valid value (raises ParamError): the old value stays,
    and callbacks that had already taken the new one get the old one back."""
    ps = params()
    applied = []
    ps.on_change(lambda n, v: applied.append(v))

    def refuse_large(name, value):
        if value > 5:
            raise ParamError(f"{name}: the motors cannot do {value}")

    ps.on_change(refuse_large)
    with pytest.raises(ParamError, match="cannot do 9"):
        ps.apply("max_velocity_mps", 9)
    assert ps["max_velocity_mps"] == 2.0 and applied == [9.0, 2.0]
    assert ps.apply("max_velocity_mps", 4) == 4.0 and ps["max_velocity_mps"] == 4.0
    ps.on_change(lambda n, v: 1 / 0 if v == 3 else None)        # a callback that fails: not applied either
    with pytest.raises(ZeroDivisionError):
        ps.apply("max_velocity_mps", 3)
    assert ps["max_velocity_mps"] == 4.0


def test_params_attribute_reads_follow_every_set_apply_and_rollback():
    """ps.NAME is a plain attribute kept in step with the values (a fast read for hot loops): it
    shows start-up sets, live applies, a refused apply's rollback and what callbacks see."""
    ps = params()
    ps.update({"retries": 5})
    assert ps.retries == 5 == ps["retries"]
    seen_in_callback = []
    ps.on_change(lambda n, v: seen_in_callback.append(ps.max_velocity_mps))
    ps.on_change(lambda n, v: (_ for _ in ()).throw(ParamError("no")) if v > 5 else None)
    assert ps.apply("max_velocity_mps", 4) == 4.0 and ps.max_velocity_mps == 4.0
    with pytest.raises(ParamError):
        ps.apply("max_velocity_mps", 9)
    assert ps.max_velocity_mps == 4.0 and seen_in_callback == [4.0, 9.0, 4.0]
    clash = ParamSet.from_declarations([Param("values", 1), Param("gain", 1.0)])   # a name ParamSet uses itself
    assert clash["values"] == 1 and clash.values == {"values": 1, "gain": 1.0} and clash.gain == 1.0


def test_params_start_only_refused_live_naming_that():
    ps = ParamSet.from_declarations([Param("strategy", "a", start_only=True), Param("gain", 1.0)])
    ps.update({"strategy": "b"})                   # start-up values (file, --param) are taken
    with pytest.raises(ParamError, match="strategy is read at start only.*still 'b'"):
        ps.apply("strategy", "c")
    assert ps["strategy"] == "b" and ps.apply("gain", 2.0) == 2.0


def test_start_only_but_marks_every_parameter_but_the_live_ones():
    marked = start_only_but(DECL, live=("retries",))
    assert [p.name for p in marked if not p.start_only] == ["retries"]
    assert [p.default for p in marked] == [p.default for p in DECL] and not any(p.start_only for p in DECL)


def test_params_load_flat_file(tmp_path):
    f = tmp_path / "p.yaml"
    f.write_text("max_velocity_mps: 4.5\nretries: 7\n")
    ps = params()
    ps.load_file(f, "planner")
    assert ps["max_velocity_mps"] == 4.5 and ps["retries"] == 7


def test_params_load_per_service_file(tmp_path):
    f = tmp_path / "stack.yaml"
    f.write_text("planner:\n  max_velocity_mps: 5.0\nmission:\n  retries: 9\n")
    ps = params()
    ps.load_file(f, "planner")
    assert ps["max_velocity_mps"] == 5.0 and ps["retries"] == 3
    other = params()
    other.load_file(f, "vio")  # a stack file without a section for this service: defaults stay
    assert other.values == params().values


@pytest.mark.parametrize("content,words", [
    (None, "cannot read parameter file"),
    ("a: [1, 2\n", "not valid YAML"),
    ("- 1\n- 2\n", "expected a mapping"),
    ("retries: lots\n", "retries: expected an integer"),
    ("planner:\n  max_velocity_mps: 99\n", "above the maximum"),
    ("bogus: 1\n", "unknown parameter 'bogus'"),
])
def test_params_bad_file_errors_name_the_file(tmp_path, content, words):
    f = tmp_path / "bad.yaml"
    if content is not None:
        f.write_text(content)
    ps = params()
    with pytest.raises(ParamError) as e:
        ps.load_file(f, "planner")
    assert str(f) in str(e.value) and words in str(e.value)
    assert ps.values == params().values


def test_params_load_empty_file_keeps_defaults(tmp_path):
    f = tmp_path / "empty.yaml"
    f.write_text("")
    ps = params()
    ps.load_file(f, "planner")
    assert ps.values == params().values


def test_parse_overrides():
    assert parse_overrides(["a=1", " b = x ", "c=k=v", "d="]) == {"a": "1", "b": "x", "c": "k=v", "d": ""}
    for bad in ("novalue", "=3"):
        with pytest.raises(ParamError, match="expected NAME=VALUE"):
            parse_overrides([bad])
