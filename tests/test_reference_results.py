"""analysis/results/reference/: the committed headline numbers are what
analysis/make_reference.py computes from the committed records."""

import json
from pathlib import Path

import pytest

from drake_grasp.evaluation.records import done_trial_ids, wilson_interval

RESULTS = Path(__file__).resolve().parents[1] / "analysis" / "results"
REFERENCE = RESULTS / "reference"

README = Path(__file__).resolve().parents[1] / "README.md"
# The README's headline rows ("Where it stands") and the summary.json entries they show.
README_ROWS = {"Table 1: objects in isolation": ("table1", "isolation"),
               "Table 1: clutter,": ("table1", "clutter"),
               "Table 1: clutter, sheet shifted": ("table1", "clutter-shift"),
               "Table 1 with depth noise: objects in isolation": ("table1_sensor_noise", "isolation"),
               "Table 1 with depth noise: clutter,": ("table1_sensor_noise", "clutter"),
               "Table 1 with depth noise: clutter, sheet shifted": ("table1_sensor_noise",
                                                                    "clutter-shift"),
               "Figure 5: within 3 cm with kinematic noise": ("figure5", ("ctr_noise", "gpd_noise")),
               "Figure 5: within 3 cm without noise": ("figure5", ("ctr", "gpd")),
               "Figure 5 (right): CNN only / CNN + CTR": ("figure5", ("cnn-only", "cnn-ctr"))}


def _readme_rows() -> dict[str, list[list[tuple[int, int]]]]:
    """{row label: [(successes, n) pairs of the "CTR here" cell, of the "GPD here" cell]}
    of the README's headline table."""
    import re

    text = README.read_text(encoding="utf-8")
    section = text.split("## Where it stands", 1)[1].split("\n## ", 1)[0]
    rows = {}
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) < 6 or not cells[0] or cells[0].startswith(("---", "experiment")):
            continue
        counts = [[(int(s), int(n)) for s, n in re.findall(r"\((\d+)/(\d+)\)", cells[i].replace(",", ""))]
                  for i in (2, 4)]
        rows[cells[0]] = counts
    return rows


def test_the_readme_headline_table_shows_the_committed_numbers(committed):
    rows = _readme_rows()
    for prefix, (block, key) in README_ROWS.items():
        label = min((r for r in rows if r.startswith(prefix)), key=len)
        ctr, gpd = rows[label]
        if block.startswith("table1"):
            want = [[(committed[block][key][c]["sim"]["successes"],
                      committed[block][key][c]["sim"]["n"])] for c in ("ctr", "gpd")]
        else:
            arms = [committed["figure5"][a] for a in key]
            pairs = [(a["within_3cm_count"], a["within_3cm_n"]) for a in arms]
            want = [pairs, []] if prefix.startswith("Figure 5 (right)") else [[pairs[0]], [pairs[1]]]
        assert [ctr, gpd] == want, (label, [ctr, gpd], want)


@pytest.fixture(scope="module")
def regenerated(tmp_path_factory, analysis_script):
    """The folder the script writes from the committed records (all arms: about 10 s)."""
    out = tmp_path_factory.mktemp("reference")
    assert analysis_script("make_reference").main(["--out", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def committed():
    return json.loads((REFERENCE / "summary.json").read_text())


def test_committed_folder_is_what_the_script_writes(regenerated, committed):
    fresh = json.loads((regenerated / "summary.json").read_text())
    assert fresh["table1"] == committed["table1"]
    assert fresh["figure5"] == committed["figure5"]
    assert fresh == committed
    for name in ("table1.md", "README.md"):
        assert (regenerated / name).read_text() == (REFERENCE / name).read_text(), name
    assert (regenerated / "figure5.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (REFERENCE / "figure5.png").is_file()


def test_summary_has_the_report_keys_and_every_source(committed):
    for key in ("experiments", "table1", "table1_sensor_noise", "figures", "paper", "targets",
                "figure5", "sources"):
        assert key in committed, key
    assert set(committed["table1"]) == {"isolation", "clutter", "clutter-shift"}
    assert set(committed["table1_sensor_noise"]) == {"isolation", "clutter", "clutter-shift"}
    assert set(committed["figure5"]) == {"init", "ctr", "ctr_noise", "gpd", "gpd_noise",
                                         "cnn-only", "cnn-ctr"}
    cells = [row[c] for key in ("table1", "table1_sensor_noise")
             for row in committed[key].values() for c in ("ctr", "gpd")]
    for entry in cells + list(committed["figure5"].values()):
        folder = entry["source"]["folder"]
        # its records: per-trial files, or packed into the folder's trials.parquet
        assert done_trial_ids(RESULTS / folder), folder
        prov = committed["sources"][folder]
        assert prov["record_code_versions"] and prov["commands"] and prov["sessions_wall_s"] > 0
        assert entry["code_versions"] and set(entry["code_versions"]) <= set(prov["record_code_versions"])


def _check_rate(successes, n, rate, ci):
    assert 0 < n and 0 <= successes <= n
    assert rate == pytest.approx(successes / n, abs=1e-12)
    assert ci == pytest.approx(list(wilson_interval(successes, n)), abs=1e-12)
    assert ci[0] <= rate <= ci[1]


def test_table1_rates_counts_and_intervals_agree(committed):
    for exp, row in committed["table1"].items():
        for cond in ("ctr", "gpd"):
            sim = row[cond]["sim"]
            _check_rate(sim["successes"], sim["n"], sim["success_rate"], sim["ci95"])


def test_sensor_noise_cells_sit_beside_their_noiseless_cells(committed):
    from drake_grasp.evaluation.proportions import mcnemar_exact_p

    for exp, row in committed["table1_sensor_noise"].items():
        for cond in ("ctr", "gpd"):
            cell, clean = row[cond], committed["table1"][exp][cond]
            sim = cell["sim"]
            _check_rate(sim["successes"], sim["n"], sim["success_rate"], sim["ci95"])
            assert cell["noiseless"] == {k: clean["sim"][k]
                                         for k in ("successes", "n", "success_rate")}
            assert cell["noiseless_source"] == clean["source"]
            assert cell["source"]["folder"].startswith("table1-sensor-noise/")
            assert cell["difference_points"] == pytest.approx(
                100 * (sim["success_rate"] - clean["sim"]["success_rate"]), abs=0.01)
            test = cell["comparison"]
            assert 0 < test["p"] <= 1
            if exp == "isolation":  # the same 120 trials, paired
                assert test["paired_trials"] == 120
                assert (test["only_with_noise"] - test["only_without_noise"]
                        == sim["successes"] - clean["sim"]["successes"])
                assert test["p"] == mcnemar_exact_p(test["only_with_noise"],
                                                    test["only_without_noise"])


def test_figure5_within_3cm_rates_agree(committed):
    for arm, stats in committed["figure5"].items():
        _check_rate(stats["within_3cm_count"], stats["within_3cm_n"], stats["within_3cm_rate"],
                    stats["within_3cm_ci95"])
        assert stats["within_3cm_n"] == 400, arm
        if arm == "init":
            assert stats["n"] is None  # INIT attempts no grasp
        else:
            _check_rate(stats["successes"], stats["n"], stats["success_rate"], stats["ci95"])


def test_a_condition_the_folder_lacks_is_named(analysis_script, tmp_path, monkeypatch, capsys):
    R = analysis_script("make_reference")
    monkeypatch.setitem(R.FIGURE5, "gpd", ("paper-bn12500-ep3/perception", "gpd"))
    with pytest.raises(SystemExit) as e:
        R.main(["--out", str(tmp_path)])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "paper-bn12500-ep3/perception: no records of condition(s) ['gpd']" in err
    assert "cnn-ctr" in err  # what it holds


def test_help(analysis_script, capsys):
    with pytest.raises(SystemExit) as e:
        analysis_script("make_reference").main(["--help"])
    assert e.value.code == 0
    assert "analysis/results/reference" in capsys.readouterr().out
