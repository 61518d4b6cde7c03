"""The reflection diagnostic (studies.reflections): its two statistics on hand-made values, and a run on a
tiny Cycles dataset."""
import csv

import pytest
import torch

from studies.reflections import main, pair_sums, texel_means, uv_texture


def test_pair_sums_keep_the_darker_view_of_every_pair_of_distinct_views():
    reflection = torch.tensor([[1.0, 0.2, 0.9], [0.5, 0.2, 0.9]])  # (V=2, T=3); texel 2 is unseen by view 1
    radiance = torch.ones(2, 3)
    seen = torch.tensor([[True, True, True], [True, True, False]])
    kept, mean_r, mean_l = pair_sums(reflection, radiance, seen, torch.ones(2, 2, 3, dtype=torch.bool)).tolist()
    assert kept == pytest.approx(2 * (0.5 + 0.2))  # both orders of the one pair, texels 0 and 1
    assert mean_r == pytest.approx(2 * (0.75 + 0.2)) and mean_l == pytest.approx(2 * 2)
    same = reflection[:1].expand(3, 3)  # a reflection every view sees alike: all of it is kept
    k, m, _ = pair_sums(same, torch.ones(3, 3), torch.ones(3, 3, dtype=torch.bool), torch.ones(3, 3, 3, dtype=torch.bool))
    assert k == pytest.approx(m)


def test_texel_means_bin_pixels_by_their_uv():
    uv = torch.tensor([[[[0.1, 0.1], [0.2, 0.2]], [[0.9, 0.9], [0.9, 0.1]]]])  # (V=1, 2, 2, 2)
    values = torch.tensor([[[1.0, 3.0], [5.0, 7.0]]])
    mask = torch.tensor([[[True, True], [True, False]]])
    means, counts = texel_means(values, uv, mask, (2, 2))  # bins: index v_bin * 2 + u_bin
    assert counts.tolist() == [[2, 0, 0, 1]] and means.tolist() == [[2.0, 0.0, 0.0, 5.0]]
    tex = uv_texture(4, 8)
    assert tex[0, 0, 0, :2].tolist() == [0.0, 1.0] and tex[0, -1, -1, :2].tolist() == [1.0, 0.0]  # top row is v = 1


def test_reflection_study_runs_on_a_cycles_dataset(tiny_glossy, tmp_path):
    assert main(["--dataset", str(tiny_glossy), "--out", str(tmp_path), "--objects", "2", "--spp", "16", "--threads", "1"]) == 0
    rows = list(csv.DictReader(open(tmp_path / "reflections.csv")))
    assert len(rows) == 4 and (tmp_path / "reflections.png").read_bytes()[:4] == b"\x89PNG"
    for r in rows:
        assert 0 < float(r["kept_by_darker_view"]) <= 1 and 0 < float(r["reflection_share"]) < 1
    ring = rows[0]  # dataset ring, upward texels: dibrpp's radiance and the Cycles images' agree
    assert float(ring["reflection_share_cycles"]) == pytest.approx(float(ring["reflection_share"]), rel=0.3)


def test_reflection_study_reports_a_missing_dataset(tmp_path, capsys):
    assert main(["--dataset", str(tmp_path / "none"), "--out", str(tmp_path)]) == 2
    assert "error:" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--dataset", str(tmp_path), "--objects", "0"])
