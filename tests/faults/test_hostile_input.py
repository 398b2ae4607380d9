"""Hostile input, property-based: malformed procedures, lab configurations, sim configurations and campaign
CSVs always get a located message and a non-zero exit code, never a traceback."""

import io
import string
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path

import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from labrunner.cli import main

ROOT = Path(__file__).resolve().parents[2]
QUICK = (ROOT / "procedures" / "quick.yaml").read_text()
LAB = """name: lab
chamber: {transport: tcp, host: 127.0.0.1, port: 5020, profile: watlow_f4}
table: {port: socket://127.0.0.1:5021}
imu: {port: /dev/ttyUSB0, rate_hz: 50}
"""
CSV_HEADER = "t_s,run,orientation,chamber_c,imu_temp_c,table_rate_dps,ax_g,ay_g,az_g,gx_dps,gy_dps,gz_dps"
CSV_ROW = "{t},1,z_up,25.0,27.1,0.0,0.001,-0.002,1.003,0.5,-0.1,0.7"

FUZZ = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                                         HealthCheck.too_slow])

scalars = st.one_of(st.none(), st.booleans(), st.integers(-10**6, 10**6), st.floats(allow_nan=True),
                    st.text(string.printable, max_size=12))
keys = st.text(string.ascii_lowercase + "_", max_size=10)
values = st.recursive(scalars, lambda inner: st.one_of(st.lists(inner, max_size=4),
                                                        st.dictionaries(keys, inner, max_size=4)), max_leaves=12)


def _run_cli(args):
    out, err = io.StringIO(), io.StringIO()
    with redirect_stdout(out), redirect_stderr(err):
        code = main([str(a) for a in args])
    return code, out.getvalue(), err.getvalue()


def _assert_rejected_with_location(code, err, path):
    assert code != 0
    assert "Traceback" not in err
    assert str(path) in err  # the message names the file (and, where it can, the line and key)


def _mutate(text, data):
    """Random edits of a valid file: delete, duplicate or replace a span, or swap a value."""
    kind = data.draw(st.sampled_from(["delete", "insert", "replace_value", "truncate"]))
    if kind == "truncate":
        return text[: data.draw(st.integers(0, len(text)))]
    i = data.draw(st.integers(0, len(text)))
    j = data.draw(st.integers(i, min(len(text), i + 30)))
    if kind == "delete":
        return text[:i] + text[j:]
    if kind == "insert":
        return text[:i] + data.draw(st.text(string.printable, max_size=20)) + text[i:]
    lines = text.splitlines()
    k = data.draw(st.integers(0, len(lines) - 1))
    if ":" in lines[k]:
        key = lines[k].split(":", 1)[0]
        lines[k] = key + ": " + yaml.safe_dump(data.draw(values), default_flow_style=True).strip().replace("\n", " ")
    return "\n".join(lines) + "\n"


@FUZZ
@given(data=st.data())
def test_fuzzed_procedures(tmp_path_factory, data):
    path = tmp_path_factory.mktemp("p") / "proc.yaml"
    text = _mutate(QUICK, data)
    path.write_text(text, encoding="utf-8")
    code, out, err = _run_cli(["check", path])
    if code == 0:
        assert "is valid" in out  # some edits leave a valid procedure (comments, equivalent values)
    else:
        _assert_rejected_with_location(code, err, path)


@FUZZ
@given(doc=values)
def test_random_yaml_documents_as_procedures_and_labs(tmp_path_factory, doc):
    d = tmp_path_factory.mktemp("y")
    for name, args in (("proc.yaml", ["check", d / "proc.yaml"]), ("lab.yaml", ["check", "--lab", d / "lab.yaml"]),
                       ("sim.yaml", ["check", "--sim-config", d / "sim.yaml"])):
        (d / name).write_text(yaml.safe_dump(doc), encoding="utf-8")
        code, out, err = _run_cli(args)
        if code != 0:
            _assert_rejected_with_location(code, err, d / name)


@FUZZ
@given(data=st.data())
def test_fuzzed_lab_configurations(tmp_path_factory, data):
    path = tmp_path_factory.mktemp("l") / "lab.yaml"
    path.write_text(_mutate(LAB, data), encoding="utf-8")
    code, out, err = _run_cli(["check", "--lab", path])
    if code != 0:
        _assert_rejected_with_location(code, err, path)


@FUZZ
@given(data=st.data(), raw=st.binary(max_size=64))
def test_fuzzed_campaign_csvs(tmp_path_factory, data, raw):
    path = tmp_path_factory.mktemp("c") / "c.csv"
    rows = [CSV_ROW.format(t=0.02 * i) for i in range(12)]
    text = CSV_HEADER + "\n" + "\n".join(rows) + "\n"
    choice = data.draw(st.sampled_from(["mutate", "binary", "cell"]))
    if choice == "binary":
        path.write_bytes(raw)
    elif choice == "cell":
        lines = text.splitlines()
        r = data.draw(st.integers(1, len(lines) - 1))
        cells = lines[r].split(",")
        c = data.draw(st.integers(0, len(cells) - 1))
        cells[c] = data.draw(st.one_of(st.sampled_from(["", "nan", "inf", "-1e999", "x_sideways", "1.5", "1e308",
                                                        "\"\"", "0x10"]), st.text(string.printable, max_size=8)))
        lines[r] = ",".join(cells)
        path.write_text("\n".join(lines) + "\n", encoding="utf-8", errors="replace")
    else:
        path.write_text(_mutate(text, data), encoding="utf-8")
    code, out, err = _run_cli(["check", "--csv", path])
    if code != 0:
        _assert_rejected_with_location(code, err, path)


def test_yaml_is_loaded_safely(tmp_path):
    path = tmp_path / "evil.yaml"
    marker = tmp_path / "pwned"
    path.write_text(f"!!python/object/apply:os.system ['touch {marker}']\n")
    code, out, err = _run_cli(["check", path])
    assert code == 2 and "not valid YAML" in err and not marker.exists()
