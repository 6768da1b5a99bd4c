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
    assert "33 rules" in res.stdout and "inputs C*, S*, Nd*, Op" in res.stdout and "outputs Ls, Rl, Ibs" in res.stdout
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
