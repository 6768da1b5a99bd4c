"""`quekaro rules check|eval` through a real subprocess (`python -m quekaro`)."""

from __future__ import annotations

import subprocess
import sys

import pytest
from fuzzy_helpers import DATA, REPO, RULES


def _quekaro(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "quekaro", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=60, check=False)


def test_check_valid_file():
    res = _quekaro("rules", "check", str(RULES))
    assert res.returncode == 0, res.stderr
    assert "48 rules" in res.stdout and "inputs C*, S*, Nd*, Op" in res.stdout and "outputs Ls, Rl, Ibs" in res.stdout
    assert len(res.stdout.strip().splitlines()) == 1


def test_check_invalid_file_names_line_variable_label():
    res = _quekaro("rules", "check", str(DATA / "invalid" / "trapezoid_d_lt_c.xml"))
    assert res.returncode == 2
    assert "trapezoid_d_lt_c.xml:9" in res.stderr and "'Ls'" in res.stderr and "'B'" in res.stderr


@pytest.mark.parametrize("name", ["billion_laughs.xml", "external_entity.xml", "not_xml.xml"])
def test_check_hostile_files(name):
    res = _quekaro("rules", "check", str(DATA / "invalid" / name))
    assert res.returncode == 2 and name in res.stderr and "Traceback" not in res.stderr


def _eval_one(c: float) -> tuple[float, float, float]:
    res = _quekaro("rules", "eval", str(RULES), "--set", f"C={c}", "--set", "S=90", "--set", "Nd=0.5",
                   "--set", "Op=4", "--range", "C=0:10", "--range", "S=0:100", "--range", "Nd=0:1")
    assert res.returncode == 0, res.stderr
    header, row = res.stdout.strip().splitlines()
    assert header == "Ls,Rl,Ibs"
    ls, rl, ibs = (float(v) for v in row.split(","))
    return ls, rl, ibs


def test_eval_with_set_and_ranges():
    # A big unit at Op VB: fewer samples than the user's (Ls < 1), depth halved at most, a narrow band;
    # C predicts the error per sample, so the complex unit keeps several times the simple one's samples.
    complex_ls, rl, ibs = _eval_one(9)
    simple_ls, _, _ = _eval_one(1)
    assert simple_ls * 2 < complex_ls < 1.0
    assert 0.5 <= rl <= 0.7 and 2 <= ibs <= 4


def test_eval_csv_both_defuzzifiers(tmp_path):
    csv_path = tmp_path / "in.csv"
    csv_path.write_text("C,S,Nd,Op\n0,0,0,0\n1,1,1,4\n0.5,0.5,0.5,2\n")
    rows = {}
    for d in ("centroid", "centre-of-sums"):
        res = _quekaro("rules", "eval", str(RULES), "--csv", str(csv_path), "--defuzzifier", d)
        assert res.returncode == 0, res.stderr
        lines = res.stdout.strip().splitlines()
        assert lines[0] == "Ls,Rl,Ibs" and len(lines) == 4
        rows[d] = lines[1:]
    assert rows["centroid"] != rows["centre-of-sums"]


def test_eval_errors_exit_2(tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("C,S,Nd,Op\n0,x,0,0\n")
    res = _quekaro("rules", "eval", str(RULES), "--csv", str(bad))
    assert res.returncode == 2 and "bad.csv:2 column S" in res.stderr
    res = _quekaro("rules", "eval", str(RULES), "--set", "C=1")
    assert res.returncode == 2 and "missing input" in res.stderr
    res = _quekaro("rules", "eval", str(RULES), "--set", "C=nan", "--set", "S=1", "--set", "Nd=1", "--set", "Op=1")
    assert res.returncode == 2 and "NaN" in res.stderr
    res = _quekaro("rules", "eval", str(RULES), "--set", "C=1", "--range", "C=1")
    assert res.returncode == 2 and "NAME=LO:HI" in res.stderr


def _eval_csv(*args: str) -> list[list[float]]:
    res = _quekaro("rules", "eval", *args)
    assert res.returncode == 0, res.stderr
    return [[float(v) for v in line.split(",")] for line in res.stdout.strip().splitlines()[1:]]


def test_eval_of_a_masyro_file_gives_what_a_render_plans():
    """MASYRO's rules run with its centre of sums, on sets rebuilt for the job's ranges (the planner's
    evaluation engine): eval must show those numbers, not the file's sets under the paper's centroid."""
    from core.rules.unit_params import Planner

    path = DATA / "masyro_fixed.xml"
    ranges = {"C": (0.0, 200.0), "Nd": (0.0, 100.0), "S": (0.0, 1e6)}
    planner = Planner(path)
    for c, nd, s in ((100.0, 50.0, 1e5), (20.0, 90.0, 7e5), (180.0, 5.0, 3e4)):
        shown = _eval_csv(str(path), "--set", f"C={c}", "--set", f"Nd={nd}", "--set", f"S={s}", "--set", "Op=15",
                          *(f"--range={k}={lo}:{hi}" for k, (lo, hi) in ranges.items()))[0]
        planned = planner.evaluation_engine(ranges).evaluate({"C": [c], "Nd": [nd], "S": [s], "Op": [15.0]})
        names = ["Ibs", "Ls", "Rl"]
        assert shown == pytest.approx([float(planned[k][0]) for k in names], rel=1e-12, nan_ok=True)
    assert planner.engine.defuzzifier == "centre-of-sums"
    args = (str(path), "--set", "C=100", "--set", "Nd=50", "--set", "S=1e5", "--set", "Op=15")
    own = {"C": (100.0, 100.0), "Nd": (50.0, 50.0), "S": (1e5, 1e5)}  # no --range: the inputs' own, as a plan
    planned = planner.evaluation_engine(own).evaluate({"C": [100.0], "Nd": [50.0], "S": [1e5], "Op": [15.0]})
    assert _eval_csv(*args)[0] == pytest.approx([float(planned[k][0]) for k in names], rel=1e-12, nan_ok=True)
    refused = _quekaro("rules", "eval", *args, "--range", "Op=0:30")  # a render keeps Op's sets as written
    assert refused.returncode == 2 and "--range Op: not an input" in refused.stderr
    args = (str(path), "--set", "C=78", "--set", "Nd=81", "--set", "S=5.3e5", "--set", "Op=15",
            *(f"--range={k}={lo}:{hi}" for k, (lo, hi) in ranges.items()))
    plain, centroid = _eval_csv(*args)[0], _eval_csv(*args, "--defuzzifier", "centroid")[0]
    assert plain == pytest.approx(_eval_csv(*args, "--defuzzifier", "centre-of-sums")[0], nan_ok=True)
    assert abs(plain[0] - centroid[0]) > 0.1, (plain, centroid)  # Ibs: the two defuzzifiers differ here


@pytest.mark.parametrize(("given", "fault"), [
    (["--range", "c=0:1"], "--range c: not an input"),  # misspelt: it was left out, and Ls changed
    (["--range", "Op=0:100"], "--range Op: not an input"),  # static: its sets are the file's
    (["--range", "C=0:1", "--range", "C=0:2"], "--range C given twice"),
    (["--range", "C=-1e308:1e308"], "beyond"),  # hi - lo overflows
])
def test_a_range_the_rules_would_not_read_as_given_is_refused(given, fault):
    res = _quekaro("rules", "eval", str(RULES), "--set", "C=0.8", "--set", "S=4096", "--set", "Nd=0.1",
                   "--set", "Op=2", *given)
    assert res.returncode == 2 and fault in res.stderr and "Traceback" not in res.stderr, res.stderr


def test_eval_csv_as_a_spreadsheet_writes_it_and_a_column_given_twice(tmp_path):
    csv_path = tmp_path / "in.csv"
    csv_path.write_bytes(b"\xef\xbb\xbfC,S,Nd,Op\n0.5,0.5,0.5,2\n")  # the BOM a spreadsheet writes
    assert len(_eval_csv(str(RULES), "--csv", str(csv_path))) == 1
    csv_path.write_text("C,S,Nd,Op,C\n0.5,0.5,0.5,2,0.1\n")
    res = _quekaro("rules", "eval", str(RULES), "--csv", str(csv_path))
    assert res.returncode == 2 and "in.csv:1: column C given twice" in res.stderr


def test_check_says_which_dialect_a_file_is_read_in():
    masyro = _quekaro("rules", "check", str(DATA / "masyro_fixed.xml")).stdout
    assert "MASYRO's dialect" in masyro and "inputs C*, " in masyro  # its C is rebuilt for each job
    assert "the paper's dialect" in _quekaro("rules", "check", str(RULES)).stdout
