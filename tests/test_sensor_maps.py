"""Register maps of real sensors (drivers/sensors/*.toml), the declared schema they are checked
against, and what makes a sample invalid: status errors and out-of-range codes, served by the
Modbus simulator over real TCP. The decoding is checked against the worked examples printed in
the sensors' own manuals (numbers we did not make)."""

from __future__ import annotations

import json
import math
import time

import jsonschema
import pytest

from smabench.drivers.base import (
    FLAG_OUT_OF_RANGE,
    FLAG_SENSOR_STATUS,
    FLAGS_INVALID,
)
from smabench.drivers.displacement import (
    SCHEMA_PATH,
    DisplacementSensor,
    SensorMapError,
    available_maps,
    decode_registers,
    encode_registers,
    load_map,
    parse_map,
)
from smabench.drivers.modbus_sim import SensorServer

RIFTEK = "riftek-rf602-80-50"
BAUMER = "baumer-om20-om30-rs485"
REAL = (RIFTEK, BAUMER)
T = 0.5  # per-request timeout: generous, a loaded machine must not fail these

pytestmark = [pytest.mark.timeout(60), pytest.mark.realtime_bench]


def test_every_shipped_map_follows_the_declared_schema():
    schema = json.loads(SCHEMA_PATH.read_text())
    jsonschema.validators.validator_for(schema).check_schema(schema)
    import tomllib

    for name in available_maps():
        path = load_map(name).source
        with open(path, "rb") as fh:
            jsonschema.validate(tomllib.load(fh), schema)  # the schema alone accepts it


def test_real_maps_name_their_document_and_the_examples_say_so():
    assert set(REAL) <= set(available_maps())
    for name in available_maps():
        m = load_map(name)
        if name in REAL:
            assert not m.example and m.document and m.section, name
        else:
            assert m.example and name.startswith("generic-"), name


def test_riftek_scaling_matches_the_manual_example():
    """RF602 manual §11.7.8 example 3: range 50 mm, D = 677 (02A5h) → X = 2.066 mm."""
    m = load_map(RIFTEK)
    assert m.position.decode([0x02A5]) == pytest.approx(2.066, abs=5e-4)
    assert m.position.decode([0x4000]) == pytest.approx(50.0)  # 4000h = the full range
    assert (m.function, m.line.baudrate, m.line.parity) == (4, 9600, "E")  # §11.3, §11.6.3
    assert [(w.address, w.values) for w in m.on_connect] == [(10, (1,)), (15, (1,))]
    assert m.position.invalid_reason(16385) and not m.position.invalid_reason(16384)


def test_baumer_float_word_order_matches_the_manual_example():
    """OM20/OM30 manual §7.2 (p. 23): 202 = 7C37h, 203 = 428Bh is 69.743 mm (low word first)."""
    m = load_map(BAUMER)
    assert m.position.decode([0x7C37, 0x428B]) == pytest.approx(69.743, abs=5e-4)
    assert m.blocks() == [(200, 13, [m.quantities["status"], m.position])]  # read whole
    assert m.position.invalid_reason(math.nan)
    assert m.quantities["status"].status_error(2) and not m.quantities["status"].status_error(1)


@pytest.mark.parametrize(
    ("word_order", "byte_order", "regs"),
    [
        ("big", "big", [0x1234, 0x5678]),  # ABCD
        ("little", "big", [0x5678, 0x1234]),  # CDAB
        ("big", "little", [0x3412, 0x7856]),  # BADC
        ("little", "little", [0x7856, 0x3412]),  # DCBA
    ],
)
def test_word_and_byte_order(word_order, byte_order, regs):
    assert encode_registers(0x12345678, "uint32", word_order, byte_order) == regs
    assert decode_registers(regs, "uint32", word_order, byte_order) == 0x12345678


@pytest.mark.parametrize("name", REAL)
def test_real_map_served_read_and_configured(name):
    """The simulator serves the map; connecting checks the identity registers and writes the
    configuration; a status error or an out-of-range code gives an invalid sample (NaN)."""
    m = load_map(name)
    with SensorServer(name, tcp_port=0) as srv:
        srv.set_position_mm(12.5)
        with DisplacementSensor(m, srv.tcp_spec, timeout_s=T) as s:
            assert srv.writes == [(w.address, list(w.values)) for w in m.on_connect]
            sample = s.read()
            assert sample.ok and sample.position_mm == pytest.approx(12.5, abs=m.position.scale)
            srv.serve_sentinel(count=1)
            bad = s.read()
            assert bad.flags & FLAG_OUT_OF_RANGE and not bad.ok and math.isnan(bad.position_mm)
            assert "position raw value" in bad.error
            assert s.read().ok  # the fault was for one request
            if "status" in m.quantities:
                srv.serve_status_error(count=2)
                for _ in range(2):
                    bad = s.read()
                    assert bad.flags & FLAG_SENSOR_STATUS and math.isnan(bad.position_mm)
                    assert bad.flags & FLAGS_INVALID
                assert s.read().ok
            assert s.stats["invalid"] == 1 + 2 * ("status" in m.quantities)
            assert srv.requests >= 4


def test_wrong_model_is_refused_at_connect():
    """A sensor whose range register says 25 mm is not the 50 mm sensor the scale is for."""
    with SensorServer(RIFTEK, tcp_port=0) as srv:
        srv.set_registers(5, [25])
        s = DisplacementSensor(RIFTEK, srv.tcp_spec, timeout_s=T)
        with pytest.raises(SensorMapError, match="register 5 reads 25.*expects 50"):
            s.connect()
        assert not s.connected
        assert srv.writes == []  # nothing written to a sensor the map does not fit


def test_on_connect_writes_are_redone_after_a_reconnect():
    with (
        SensorServer(BAUMER, tcp_port=0) as srv,
        DisplacementSensor(BAUMER, srv.tcp_spec, timeout_s=T, reconnect_interval_s=0) as s,
    ):
        assert s.read().ok
        srv.stop()
        assert not s.read_or_flag().ok
        srv.start()
        deadline = time.monotonic() + 10
        while not s.read_or_flag().ok:
            assert time.monotonic() < deadline, "no reconnect"
        assert srv.writes == [(800, [0]), (800, [0])]


def test_adapter_latency_delays_every_answer():
    """An FTDI adapter's latency timer holds each answer (here 30 ms): the read cannot be
    faster than that (a lower bound: true on any machine)."""
    with (
        SensorServer(BAUMER, tcp_port=0, adapter_latency_s=0.03) as srv,
        DisplacementSensor(BAUMER, srv.tcp_spec, timeout_s=T) as s,
    ):
        lat = [s.read().latency_s for _ in range(3)]
    assert min(lat) >= 0.03
    with pytest.raises(ValueError, match="adapter latency"):
        SensorServer(BAUMER, adapter_latency_s=2.0)


GOOD = {"registers": {"position": {"address": 0, "type": "int32", "scale": 0.001}}}


@pytest.mark.parametrize(
    ("patch", "where", "words"),
    [
        ({"position": {"address": 0, "type": "int32", "scale": math.nan}},
         "[registers.position].scale", "finite"),
        ({"position": {"address": 0, "type": "uint16", "valid_range": [9, 1]}},
         "[registers.position].valid_range", "low end above high end"),
        ({"position": {"address": 0, "type": "uint16", "byte_order": "middle"}},
         "[registers.position].byte_order", "bad value"),
        ({"position": {"address": 0, "type": "float32"},
          "status": {"address": 1, "type": "uint16", "error_values": [2]}},
         "[registers.status].address", "overlaps"),
        ({"position": {"address": 0, "type": "uint16", "scale": 0}},
         "[registers.position].scale", "must not be 0"),
    ],
)
def test_schema_errors_name_the_key(patch, where, words):
    with pytest.raises(SensorMapError) as info:
        parse_map({"registers": patch}, source="x.toml")
    assert "x.toml" in str(info.value) and where in str(info.value)
    assert words in str(info.value)


def test_blocks_and_writes_are_checked():
    with pytest.raises(SensorMapError, match=r"\[registers.position\].address: not inside"):
        parse_map({**GOOD, "block": [{"address": 10, "count": 2}]})
    with pytest.raises(SensorMapError, match=r"\[\[on_connect\]\] #1: missing.*|description"):
        parse_map({**GOOD, "on_connect": [{"address": 3, "values": [1]}]})
    with pytest.raises(SensorMapError, match=r"\[\[check\]\] #1.expect"):
        parse_map({**GOOD, "check": [{"address": 3, "expect": 70000, "description": "x"}]})


def test_latency_timer_of_the_adapter_is_read_and_warned_about(tmp_path, monkeypatch, caplog):
    """The driver reads the FTDI latency timer from sysfs (here a stand-in folder) and warns
    when it is above 1 ms; a port without one (a pty, another chip) gives None."""
    import smabench.drivers.displacement as d

    (tmp_path / "ttyUSB7").mkdir()
    (tmp_path / "ttyUSB7" / "latency_timer").write_text("16\n")
    monkeypatch.setattr(d, "LATENCY_TIMER_SYSFS", str(tmp_path / "{tty}" / "latency_timer"))
    link = tmp_path / "by-id-adapter"
    link.symlink_to(tmp_path / "ttyUSB7")  # /dev/serial/by-id/… style names are followed
    assert d.adapter_latency_ms(str(link)) == 16
    assert d.adapter_latency_ms("/dev/pts/0") is None
    s = DisplacementSensor(BAUMER, f"rtu:{tmp_path / 'ttyUSB7'}", timeout_s=T)
    with (
        caplog.at_level("WARNING", logger="smabench.drivers.displacement"),
        pytest.raises(d.SensorLinkLost),
    ):
        s.connect()  # not a serial port: the connect fails, after the check
    assert any("latency timer is 16 ms" in r.getMessage() for r in caplog.records)


def test_a_position_outside_the_sensor_range_is_served_as_out_of_range():
    """The plant can move the slider where a real sensor cannot measure (below 0 on the RF602):
    the simulator then serves the map's out-of-range code, not a failing device."""
    with SensorServer(RIFTEK, tcp_port=0) as srv:
        srv.set_source("position", lambda: -1.0)
        with DisplacementSensor(RIFTEK, srv.tcp_spec, timeout_s=T) as s:
            sample = s.read()
        assert sample.flags == FLAG_OUT_OF_RANGE and math.isnan(sample.position_mm)


@pytest.mark.slow  # a mock bench process: about 6 s on a loaded machine
def test_mock_bench_serves_the_chosen_map_behind_an_adapter_latency():
    """`smabench mock --sensor-map … --adapter-latency-ms …` end to end (its own process), with
    the fault injection of its control input."""
    from smabench.bench.headless import MockProcess

    with (
        MockProcess(["--sensor-map", BAUMER, "--adapter-latency-ms", "30"]) as mock,
        DisplacementSensor(BAUMER, mock.ports.sensor_tcp, timeout_s=T) as s,
    ):
        sample = s.read()
        assert sample.ok and sample.latency_s >= 0.03
        mock.send("sensor-status-error 1000")
        deadline = time.monotonic() + 10
        while not s.read().flags & FLAG_SENSOR_STATUS:
            assert time.monotonic() < deadline, "status error never served"


# ------------------------------------------------ maps generated from the schema (Hypothesis)
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

SCHEMA = json.loads(SCHEMA_PATH.read_text())
DEFS = SCHEMA["$defs"]
TOP = SCHEMA["properties"]
MAPS = settings(max_examples=80, deadline=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture,
                                       HealthCheck.too_slow])  # fmt: skip
WIDTH = {"int16": 1, "uint16": 1, "int32": 2, "uint32": 2, "float32": 2}
INT_RANGE = {"int16": (-(2**15), 2**15 - 1), "uint16": (0, 2**16 - 1),
             "int32": (-(2**31), 2**31 - 1), "uint32": (0, 2**32 - 1)}  # fmt: skip
text = st.text(st.characters(blacklist_categories=("Cs",)), max_size=20)  # TOML holds no surrogates


def leaf(spec: dict) -> st.SearchStrategy:
    """Values the schema accepts for one leaf (enum, const, integer, number, string, boolean)."""
    spec = DEFS[spec["$ref"].rsplit("/", 1)[1]] if "$ref" in spec else spec
    if "enum" in spec:
        return st.sampled_from(spec["enum"])
    if "const" in spec:
        return st.just(spec["const"])
    kind = spec.get("type")
    if kind == "integer":
        return st.integers(spec.get("minimum", -(2**40)), spec.get("maximum", 2**40))
    if kind == "number":
        lo = spec.get("minimum", spec.get("exclusiveMinimum", -1e6))
        hi = spec.get("maximum", spec.get("exclusiveMaximum", 1e6))
        return st.floats(lo, hi, exclude_min="exclusiveMinimum" in spec,
                         exclude_max="exclusiveMaximum" in spec)  # fmt: skip
    if kind == "string":
        return text.filter(lambda s: len(s) >= spec.get("minLength", 0))
    if kind == "boolean":
        return st.booleans()
    raise AssertionError(f"no strategy for {spec}")  # a new schema leaf: teach the generator


@st.composite
def some_of(draw, props: dict, skip: tuple[str, ...] = ()) -> dict:
    """A table holding any subset of the schema's leaf ``props``."""
    keys = draw(st.sets(st.sampled_from(sorted(k for k in props if k not in skip))))
    return {k: draw(leaf(props[k])) for k in sorted(keys)}


scale = st.floats(1e-6, 1e3).flatmap(lambda m: st.sampled_from([m, -m]))


@st.composite
def quantity(draw, name: str, address: int, dtype: str) -> dict:
    spec = DEFS["status" if name == "status" else "value"]["properties"]
    q = {"address": address, "type": dtype}
    q.update(draw(some_of(spec, skip=("address", "type", "scale", "offset", "valid_range",
                                      "sentinels", "units", "error_mask", "error_values"))))
    if name == "status":
        if draw(st.booleans()):
            q["error_mask"] = draw(leaf(spec["error_mask"]))
        if draw(st.booleans()):
            q["error_values"] = draw(st.lists(st.integers(0, 2**16 - 1), max_size=4))
        return q
    raw = st.floats(-1e9, 1e9, width=32) if dtype == "float32" else st.integers(*INT_RANGE[dtype])
    if draw(st.booleans()):
        q["scale"] = draw(scale)
    if draw(st.booleans()):
        q["offset"] = draw(st.floats(-1e3, 1e3))
    if draw(st.booleans()):
        q["valid_range"] = sorted(draw(st.lists(raw, min_size=2, max_size=2)))
    if draw(st.booleans()):
        q["sentinels"] = draw(st.lists(raw, max_size=3))
    if name == "position" and draw(st.booleans()):
        q["units"] = "mm"
    elif name != "position" and draw(st.booleans()):
        q["units"] = draw(text)
    return q


@st.composite
def valid_maps(draw) -> dict:
    """Any map the schema and the register layout accept: the schema's own enums and bounds,
    quantities at non-overlapping addresses, blocks that hold them, writes and checks."""
    names = ["position"] + draw(st.lists(st.sampled_from(["temperature", "status"]),
                                         unique=True))  # fmt: skip
    names = draw(st.permutations(names))
    regs: dict[str, dict] = {}
    address = draw(st.integers(0, 65000))
    for name in names:
        types = DEFS["status" if name == "status" else "value"]["properties"]["type"]["enum"]
        dtype = draw(st.sampled_from(types))
        if address + WIDTH[dtype] > 65536:
            break
        regs[name] = draw(quantity(name, address, dtype))
        address += WIDTH[dtype] + draw(st.integers(0, 3))
    data: dict = {"registers": regs}
    if draw(st.booleans()):
        data["sensor"] = draw(some_of(TOP["sensor"]["properties"]))
    if draw(st.booleans()):
        data["line"] = draw(some_of(TOP["line"]["properties"]))
    if draw(st.booleans()):  # one read per quantity, or one for all when they fit
        spans = [(q["address"], WIDTH[q["type"]]) for q in regs.values()]
        lo, hi = min(a for a, _ in spans), max(a + n for a, n in spans)
        data["block"] = ([{"address": lo, "count": hi - lo}] if hi - lo <= 125 else
                         [{"address": a, "count": n} for a, n in spans])  # fmt: skip
    u16 = st.integers(0, 65535)
    data["on_connect"] = draw(st.lists(st.fixed_dictionaries(
        {"address": u16, "values": st.lists(u16, min_size=1, max_size=4),
         "description": text.filter(bool)}), max_size=2))  # fmt: skip
    data["check"] = draw(st.lists(st.fixed_dictionaries(
        {"address": u16, "expect": u16, "description": text.filter(bool)},
        optional={"function": st.sampled_from([3, 4])}), max_size=2))  # fmt: skip
    return data


def _raw_values(q) -> st.SearchStrategy:
    if q.dtype == "float32":
        return st.floats(width=32, allow_nan=False)
    return st.integers(*INT_RANGE[q.dtype])


@given(data=valid_maps(), pick=st.data())
@MAPS
def test_any_valid_map_loads_from_its_file_and_its_codec_round_trips(tmp_path_factory, data,
                                                                     pick):  # fmt: skip
    import tomli_w

    jsonschema.validate(data, SCHEMA)  # the generator makes what the schema declares
    path = tmp_path_factory.mktemp("map") / "generated.toml"
    path.write_text(tomli_w.dumps(data), encoding="utf-8")
    m = load_map(path)
    assert m == parse_map(data, source=str(path), default_name="generated")
    assert m.name == data.get("sensor", {}).get("name", "generated")
    assert [(w.address, list(w.values)) for w in m.on_connect] == [
        (w["address"], w["values"]) for w in data["on_connect"]]  # fmt: skip
    for name, spec in data["registers"].items():
        q = m.quantities[name]
        assert (q.address, q.dtype, q.count) == (spec["address"], spec["type"], WIDTH[q.dtype])
        covered = [b for b in m.blocks() if q in b[2]]
        assert len(covered) == 1 and covered[0][0] <= q.address
        assert q.address + q.count <= covered[0][0] + covered[0][1] <= covered[0][0] + 125
        raw = pick.draw(_raw_values(q))
        regs = q.encode_raw(raw)
        assert len(regs) == q.count and all(0 <= r <= 0xFFFF for r in regs)
        assert q.raw(regs) == raw  # the registers hold the raw value exactly
        if name == "status":
            assert q.decode(regs) == raw
            continue
        value = q.decode(regs)
        if q.dtype != "float32":  # integers: the physical value encodes to the same registers
            assert q.encode(value) == regs
        if q.invalid_reason(raw) == "":
            assert raw not in q.sentinels and math.isfinite(raw)
        for bad in q.sentinels:
            assert q.invalid_reason(bad)
        if q.sentinels or q.valid_range is not None or q.dtype == "float32":
            assert q.invalid_reason(q.invalid_raw)


def _paths(node: dict, prefix: tuple = ()):
    """Every (path, value) of a generated map, tables and arrays included."""
    for k, v in node.items():
        yield (*prefix, k), v
        if isinstance(v, dict):
            yield from _paths(v, (*prefix, k))
        elif isinstance(v, list):
            for i, item in enumerate(v):
                if isinstance(item, dict):
                    yield from _paths(item, (*prefix, k, i))


def _set(data: dict, path: tuple, value) -> None:
    node = data
    for k in path[:-1]:
        node = node[k]
    node[path[-1]] = value


def _schema_of(path: tuple) -> dict | None:
    """The schema of the leaf at ``path`` of a map (None for a table or an array)."""
    spec: dict = SCHEMA
    for k in path:
        if "$ref" in spec:
            spec = DEFS[spec["$ref"].rsplit("/", 1)[1]]
        if isinstance(k, int):
            spec = spec.get("items", {})
        else:
            spec = spec.get("properties", {}).get(k, {})
    if "$ref" in spec:
        spec = DEFS[spec["$ref"].rsplit("/", 1)[1]]
    return None if spec.get("type") in ("object", "array") else spec


@st.composite
def invalid_maps(draw) -> tuple[dict, str]:
    """A valid map broken in one way the schema or the layout forbids; (map, what broke)."""
    data = draw(valid_maps())
    leaves = [(p, v) for p, v in _paths(data) if not isinstance(v, (dict, list))
              and _schema_of(p) is not None]  # fmt: skip
    how = draw(st.sampled_from(["unknown key", "wrong type", "not in enum", "out of bounds",
                                "missing", "zero scale", "reversed range", "overlap",
                                "non-finite", "outside block"]))  # fmt: skip
    if how == "unknown key":
        tables = [()] + [p for p, v in _paths(data) if isinstance(v, dict) and p != ("registers",)]
        where = draw(st.sampled_from(tables))
        allowed = set(_schema_at(where).get("properties", {}))
        key = draw(st.text(min_size=1, max_size=12).filter(lambda k: k not in allowed))
        node = data
        for k in where:
            node = node[k]
        node[key] = draw(st.one_of(st.integers(0, 9), text))
    elif how == "wrong type":
        path, value = draw(st.sampled_from(leaves))
        _set(data, path, {bool: "yes", int: "1", float: "1.5", str: 7}[type(value)])
    elif how == "not in enum":
        enums = [(p, _schema_of(p)["enum"]) for p, _ in leaves if "enum" in _schema_of(p)]
        path, enum = draw(st.sampled_from(enums))  # registers.position.type is always one
        _set(data, path, draw(st.sampled_from(["", "BIG", "float64", 5, 0]).filter(
            lambda v: v not in enum)))  # fmt: skip
    elif how == "out of bounds":
        bounded = [(p, s) for p, s in ((p, _schema_of(p)) for p, _ in leaves)
                   if s.get("type") == "integer" and "maximum" in s]  # fmt: skip
        if not bounded:  # registers.position.address is always there
            raise AssertionError("no bounded integer")
        path, spec = draw(st.sampled_from(bounded))
        _set(data, path, draw(st.sampled_from([spec["maximum"] + 1, spec.get("minimum", 0) - 1])))
    elif how == "missing":
        path = draw(st.sampled_from([("registers", "position"), ("registers", "position", "type"),
                                     ("registers", "position", "address")]))  # fmt: skip
        node = data
        for k in path[:-1]:
            node = node[k]
        del node[path[-1]]
    elif how == "zero scale":
        data["registers"]["position"]["scale"] = draw(st.sampled_from([0, 0.0, -0.0]))
    elif how == "reversed range":
        lo = draw(st.integers(0, 1000))
        data["registers"]["position"]["valid_range"] = [lo + draw(st.integers(1, 9)), lo]
    elif how == "overlap":
        pos = data["registers"]["position"]
        data["registers"]["temperature"] = {"address": pos["address"] + WIDTH[pos["type"]] - 1,
                                            "type": "int16"}  # fmt: skip
        data["registers"].pop("status", None)
        data.pop("block", None)
        if pos["address"] + WIDTH[pos["type"]] - 1 > 65535:
            raise AssertionError("unreachable: position fits")
    elif how == "non-finite":
        numbers = [p for p, v in leaves if isinstance(v, float)] + [
            ("registers", "position", "offset")]  # fmt: skip
        _set(data, draw(st.sampled_from(numbers)), draw(st.sampled_from([math.nan, math.inf,
                                                                         -math.inf])))  # fmt: skip
    else:  # a block that holds no quantity
        pos = data["registers"]["position"]
        far = (pos["address"] + 300) % 65000
        data["block"] = [{"address": far, "count": 1}]
    return data, how


def _schema_at(path: tuple) -> dict:
    spec: dict = SCHEMA
    for k in path:
        if "$ref" in spec:
            spec = DEFS[spec["$ref"].rsplit("/", 1)[1]]
        spec = spec.get("items", {}) if isinstance(k, int) else spec["properties"][k]
    return DEFS[spec["$ref"].rsplit("/", 1)[1]] if "$ref" in spec else spec


@given(broken=invalid_maps())
@MAPS
def test_any_invalid_map_is_one_line_naming_the_file_and_the_key(tmp_path_factory, broken):
    import tomli_w

    data, how = broken
    path = tmp_path_factory.mktemp("bad") / "broken.toml"
    path.write_text(tomli_w.dumps(data), encoding="utf-8")
    with pytest.raises(SensorMapError) as info:
        load_map(path)
    message = str(info.value)
    assert message.startswith(f"{path}: "), message
    assert len(message.splitlines()) == 1 and message.isprintable(), (how, message)
    assert "[" in message or "(top level)" in message, (how, message)  # names where
