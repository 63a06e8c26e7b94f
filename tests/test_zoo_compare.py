"""`bridge-zoo compare NAME WORKDIR` and the real-image checks it runs (`bridge_jax.eval.real_checks`).

The scorers are checked against numbers computed here with numpy alone, for stand-in methods whose answer is
known: the ground truth itself (every error 0) and zero motion (every error the ground truth's own length).
"""
import dataclasses
import json

import numpy as np
import pytest

from bridge_jax import inference, metrics, zoo
from bridge_jax.polish import DEFAULT_CONFIG as POLISH_DEFAULTS
from bridge_jax.eval import real_checks
from bridge_jax.zoo.__main__ import main


class GroundTruth:
    """A method that answers every pair of `pairs` with its exact flow (looked up by the frame-t image)."""

    def __init__(self, pairs):
        self.flows = {id(p["frame_t"]): p["flow"] for p in pairs}

    def predict(self, jobs, batch=None):
        assert all(task == "flow" for task, _, _ in jobs)
        return [self.flows[id(a)] for _, a, _ in jobs]


def zero_motion_flow_numbers(gt, valid, noc=None):
    """EPE and Fl (%) of a zero prediction: the error is the ground truth's length, an outlier where that is
    over 3 px (and so over 5 % of itself)."""
    length = np.hypot(gt[..., 0].astype(np.float64), gt[..., 1].astype(np.float64))
    out = {"epe_all": length[valid].mean(), "fl_all": 100.0 * (length[valid] > 3).mean()}
    if noc is not None:
        out["epe_noc"] = length[noc].mean()
    return out


def zero_motion_disparity_numbers(disp, valid):
    d = disp.astype(np.float64)[valid]
    return {"epe_all": d.mean(), "d1_all": 100.0 * (d > 3).mean()}


def zero_motion_edge_numbers(disp, valid):
    """Near depth edges (the band `metrics.depth_edge_band` marks, itself checked by hand in test_metrics) zero
    disparity errs by the true disparity and is never too large."""
    d = disp.astype(np.float64)[metrics.depth_edge_band(disp, valid)]
    return {"epe_edge": d.mean(), "d1_edge": 100.0 * (d > 3).mean(), "fat_edge": 0.0}


def zero_motion_numbers(check, data):
    """The numbers a zero-motion method gets on `check` (its `build` data), computed here."""
    if check == "motorcycle":
        # the strip the right view cannot see: columns x < d (checked by hand in test_metrics)
        strip = data["valid"] & (np.arange(data["disp"].shape[1])[None, :] < data["disp"])
        d = data["disp"].astype(np.float64)[strip]
        return {**zero_motion_disparity_numbers(data["disp"], data["valid"]),
                **zero_motion_edge_numbers(data["disp"], data["valid"]),
                "epe_outview": d.mean(), "d1_outview": 100.0 * (d > 3).mean()}
    if check == "homography":
        rows = [zero_motion_flow_numbers(p["flow"], p["valid"], p["noc"]) for p in data]
    else:  # heldout_synthetic
        rows = []
        for fr in data:
            f = zero_motion_flow_numbers(fr.gt["flow_occ"], fr.gt["flow_occ_valid"], fr.gt["flow_noc_valid"])
            d = zero_motion_disparity_numbers(fr.gt["disp_occ_0"], fr.gt["disp_occ_0"] > 0)
            e = zero_motion_edge_numbers(fr.gt["disp_occ_0"], fr.gt["disp_occ_0"] > 0)
            rows.append({"flow_epe_all": f["epe_all"], "flow_epe_noc": f["epe_noc"], "fl_all": f["fl_all"],
                         "disp_epe_all": d["epe_all"], "d1_all": d["d1_all"], "disp_epe_edge": e["epe_edge"],
                         "d1_edge": e["d1_edge"], "fat_edge": e["fat_edge"]})
    return {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}


@pytest.mark.parametrize("check", ["homography", "shifts", "zooms"])
def test_the_exact_flow_scores_zero_error(check):
    pairs = real_checks.build(check, limit=3)
    assert len(pairs) == 3
    numbers, first = real_checks.score(GroundTruth(pairs), check, pairs)
    np.testing.assert_array_equal(first, pairs[0]["flow"])
    for metric, value in numbers.items():
        assert value == pytest.approx(1.0 if metric.startswith("gain") else 0.0, abs=1e-9), metric


@pytest.mark.parametrize("check, limit", [("motorcycle", None), ("homography", 2), ("heldout_synthetic", 2)])
def test_zero_motion_scores_the_length_of_the_true_motion(check, limit):
    data = real_checks.build(check, limit=limit)
    numbers, first = real_checks.score(real_checks.ZeroMotion(), check, data)
    expected = zero_motion_numbers(check, data)
    assert numbers.keys() == expected.keys()
    for metric, value in expected.items():
        assert numbers[metric] == pytest.approx(value, rel=1e-6), metric
    assert not first.any()
    assert numbers[next(iter(numbers))] > 0.5  # the checks do move: zero motion is far from exact


def test_limit_keeps_the_first_inputs_of_the_full_set():
    """A quick look (`limit`) scores the first pairs of the very set the card's numbers came from."""
    full, first_two = real_checks.homography_set(), real_checks.build("homography", limit=2)
    assert len(full) == 3 * len(real_checks.photos.HELDOUT_PHOTOS)
    for a, b in zip(full[:2], first_two):
        np.testing.assert_array_equal(a["frame_t1"], b["frame_t1"])
        np.testing.assert_array_equal(a["flow"], b["flow"])
    synthetic = real_checks.build("heldout_synthetic", limit=1)
    np.testing.assert_array_equal(synthetic[0].images["left_t1"],
                                  real_checks.heldout_synthetic(2)[0].images["left_t1"])


CARD = {"default_working_size": "192x384", "default_refine": 1, "default_polish": "photometric",
        "real_images": {"heldout_synthetic": {"192x384": {"flow_epe_all": 10.0}},
                        "motorcycle": {"192x384": {"epe_all": 2.0, "d1_all": 15.0},
                                       "trained": {"epe_all": 9.0, "d1_all": 90.0}},
                        "homography": {"trained": {"epe_all": 1.0}},  # not measured at the card's size
                        "a_check_of_a_later_version": {"192x384": {"epe_all": 1.0}}}}


def test_card_numbers_are_those_at_the_cards_settings():
    assert real_checks.card_settings(CARD) == {"working_size": "192x384", "refine": 1, "symmetry": "none",
                                               "polish": "photometric"}
    got = real_checks.card_numbers(CARD, "photometric")
    assert list(got) == ["motorcycle", "heldout_synthetic"]  # in the order the checks run, known checks only
    assert got["motorcycle"] == {"epe_all": 2.0, "d1_all": 15.0}
    assert real_checks.card_numbers(CARD, "none") is None  # this card holds no polish-none numbers
    with_none = dict(CARD, real_images_polish_none={"motorcycle": {"192x384": {"epe_all": 3.0, "d1_all": 20.0}}})
    assert real_checks.card_numbers(with_none, "none") == {"motorcycle": {"epe_all": 3.0, "d1_all": 20.0}}
    # a card measured without a polish: its numbers are the polish-none ones
    plain = dict(CARD, default_polish="none")
    assert real_checks.card_numbers(plain, "none") == real_checks.card_numbers(CARD, "photometric")


def test_rows_and_table_say_which_numbers_are_at_least_as_good():
    card = {"motorcycle": {"epe_all": 2.0, "d1_all": 15.0}, "shifts": {"gain_vertical": 0.97}}
    measured = {"motorcycle": {"epe_all": 1.5, "d1_all": 15.0004}, "shifts": {"gain_vertical": 1.02}}
    measured_none = {"motorcycle": {"epe_all": 2.5, "d1_all": 20.0}, "shifts": {"gain_vertical": 0.9}}
    rows = real_checks.comparison_rows(card, measured, None, measured_none)
    assert [(r["check"], r["metric"]) for r in rows] == [("motorcycle", "epe_all"), ("motorcycle", "d1_all"),
                                                          ("shifts", "gain_vertical")]
    assert rows[0]["difference"] == pytest.approx(-0.5) and rows[0]["as_good"]
    assert rows[1]["as_good"]  # 0.0004 worse: a tie at the table's precision
    assert real_checks.at_least_as_good("epe_all", 9.5624, 9.5615)  # 0.01 % worse: the spread between CPU kinds
    assert not real_checks.at_least_as_good("epe_all", 0.0016, 0.0)  # 0.002 at the table's precision
    assert rows[2]["as_good"]  # a gain: 1.02 is closer to 1 than 0.97
    assert not real_checks.comparison_rows(card, {"motorcycle": {"epe_all": 2.01}})[0]["as_good"]  # 0.5 % worse
    assert rows[0]["card_polish_none"] is None and rows[0]["workdir_polish_none"] == 2.5
    head, rule, *body = real_checks.comparison_table(rows, "photometric")
    assert [c.strip() for c in head.strip("|").split("|")] == [
        "check", "metric", "card (polish photometric)", "workdir (polish photometric)", "difference",
        "at least as good", "card (polish none)", "workdir (polish none)"]
    assert set(rule) <= set("|-:")
    assert [c.strip() for c in body[0].strip("|").split("|")] == [
        "motorcycle", "epe_all", "2.000", "1.500", "-0.500", "yes", "–", "2.500"]
    assert [c.strip() for c in body[1].strip("|").split("|")][2:6] == ["15.000", "15.000", "+0.000", "yes"]
    assert len({len(line) for line in [head, rule] + body}) == 1  # aligned columns
    # without the polish-none run, and a check the card lacks
    head, _, row = real_checks.comparison_table(real_checks.comparison_rows(None, {"zooms": {"epe_expand": 0.3}}),
                                                "none")
    assert [c.strip() for c in row.strip("|").split("|")] == ["zooms", "epe_expand", "–", "0.300", "–", "–"]
    assert "card (polish none)" in head and head.count("|") == 7


@pytest.fixture
def zero_motion_checkpoint(monkeypatch):
    """`inference.load_predictor` answering zero motion for any checkpoint, recording what it was asked for."""
    calls = []

    def load(path, **kwargs):
        calls.append(dict(kwargs, path=path))
        return real_checks.ZeroMotion()

    monkeypatch.setattr(inference, "load_predictor", load)
    return calls


def test_compare_runs_the_checkpoint_at_the_cards_settings(zero_motion_checkpoint):
    card = json.loads((zoo.ZOO_DIR / "demo.json").read_text())
    result = real_checks.compare_with_card("demo", "work/x", limit=1)
    assert [(c["path"], c["size"], c["test_time"]) for c in zero_motion_checkpoint] == [
        ("work/x", (192, 384), inference.TestTime(1, "none", "photometric")),
        ("work/x", (192, 384), inference.TestTime(1, "none", "none"))]
    checks = ["motorcycle", "homography", "heldout_synthetic"]
    assert list(result["runs"]["photometric"]["numbers"]) == checks
    for check in checks:
        expected = zero_motion_numbers(check, real_checks.build(check, limit=1))
        expected = {k: v for k, v in expected.items() if k in card["real_images"][check]["192x384"]}  # the card's
        for polish in ("photometric", "none"):
            got = result["runs"][polish]["numbers"][check]
            assert got == pytest.approx(expected, rel=1e-6)
        for row in (r for r in result["rows"] if r["check"] == check):
            assert row["card"] == card["real_images"][check]["192x384"][row["metric"]]
            assert row["workdir"] == pytest.approx(expected[row["metric"]], rel=1e-6)
            assert row["difference"] == pytest.approx(row["workdir"] - row["card"])
            assert row["as_good"] == (row["workdir"] <= row["card"])  # never close here: no ties
            assert row["card_polish_none"] is None  # demo's card holds no polish-none numbers
    assert not any(r["as_good"] for r in result["rows"])  # zero motion is no match for the demo model
    # the checkpoint is polished with the parameters the card was measured with, whatever its own lineage says
    assert all(c["polish_config"] == dataclasses.replace(POLISH_DEFAULTS, **zoo.card_polish_settings("demo"))
               for c in zero_motion_checkpoint)
    zero_motion_checkpoint.clear()
    real_checks.compare_with_card("long", "work/x", polish="card", limit=1)
    assert [c["polish_config"].variational_sigma for c in zero_motion_checkpoint] == [
        zoo.info("long")["default_polish_settings"]["variational_sigma"]]


def test_compare_command_prints_the_table_and_writes_json(zero_motion_checkpoint, tmp_path, capsys):
    out = tmp_path / "compare.json"
    assert main(["compare", "long", str(tmp_path), "--polish", "card", "--limit", "1", "--json", str(out)]) == 0
    polish = zoo.info("long")["default_polish"]
    assert [c["test_time"].polish for c in zero_motion_checkpoint] == [polish]
    assert zero_motion_checkpoint[0]["size"] == "native" and zero_motion_checkpoint[0]["test_time"].symmetry == "flips"
    text = capsys.readouterr().out
    assert "long's card" in text and f"working size native, refine 1, symmetry flips, polish {polish}" in text
    assert "--limit" in text  # says the numbers are over fewer inputs than the card's
    table = [line for line in text.splitlines() if line.startswith("| ")]
    assert len(table) == 1 + 2 + 3 + 5  # the header, then motorcycle, homography and held-out synthetic metrics
    assert "polish none" not in table[0]
    saved = json.loads(out.read_text())
    assert saved["rows"][0]["check"] == "motorcycle" and saved["limit"] == 1
    assert saved["rows"][0]["card"] == zoo.info("long")["real_images"]["motorcycle"]["native"]["epe_all"]


@pytest.mark.parametrize("args, names", [
    (["compare", "nosuchmodel", "."], ["NAME", "nosuchmodel", "demo, long"]),
    (["compare", "upstream_ver_a", "."], ["NAME", "upstream_ver_a", "not a shipped model"]),
    (["compare", "long", "{tmp}"], ["{tmp}", "not a bridge_jax checkpoint"]),
    (["compare", "long", "{tmp}/missing"], ["{tmp}/missing", "does not exist"]),
    (["compare", "long", "long", "--limit", "0"], ["--limit 0"]),
    (["compare", "long", "long", "--json", "{tmp}"], ["--json {tmp}", "folder"]),
])
def test_compare_refuses_bad_input_with_one_line(args, names, tmp_path, capsys):
    args = [a.format(tmp=tmp_path) for a in args]
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("error: ")
    for name in names:
        assert name.format(tmp=tmp_path) in err


@pytest.mark.slow
def test_long_compared_with_itself_reproduces_its_card():
    """The shipped `long` scored by this module at its card's settings gets the card's numbers, which
    experiments/real_images.py measured (before the checks moved into the package) on another machine: the
    same to a few thousandths (CPU kinds round differently)."""
    result = real_checks.compare_with_card("long", "long", polish="card")
    assert len(result["rows"]) == 10
    for row in result["rows"]:
        tolerance = 0.02 if row["metric"] in ("d1_all", "fl_all") else 0.005  # percentages / pixels
        assert row["workdir"] == pytest.approx(row["card"], abs=tolerance), row


def test_compare_scores_a_real_checkpoint_folder(tiny_checkpoint, capsys):
    """A params dir (random tiny weights) at the `demo` card's settings, one input per check: the command runs
    the real predictor end to end and prints a number in every cell of WORKDIR's column."""
    assert main(["compare", "demo", tiny_checkpoint, "--polish", "card", "--limit", "1"]) == 0
    table = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| ")][1:]  # after the header
    assert len(table) == 2 + 3 + 5
    for line in table:
        workdir = line.strip("|").split("|")[3].strip()
        assert np.isfinite(float(workdir)), line
