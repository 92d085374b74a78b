"""ais.load_traj (tracktable .traj files) and models.moored."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.linalg import expm

import torchsde_lti as tl
from torchsde_lti.data import ais


def _line(name_field: str, trailing: str = "") -> str:
    head = "*T*,uuid,terrestrial,2,0,*P*,terrestrial,2,1,1,2,heading,1,vessel-name,2,"
    pts = [f"42,2020-06-30 00:00:0{i},-74.0{i},40.6{i},10,{name_field}" for i in (1, 2)]
    return head + ",".join(pts) + trailing


@pytest.mark.parametrize("name_field, trailing", [("SHIP", ""), ("", ","), ("A, B", ""), ("A, B", ",")])
def test_parse_traj_line_string_properties(name_field: str, trailing: str) -> None:
    obj, pts = ais._parse_traj_line(_line(name_field, trailing).split(","))
    assert obj == 42 and len(pts) == 2
    assert pts[1][1] == pytest.approx(-74.02) and pts[1][2] == pytest.approx(40.62)
    assert (pts[1][0] - pts[0][0]).total_seconds() == 1.0


def test_load_traj_file(tmp_path) -> None:
    f = tmp_path / "x.traj"
    lines = [_line("SHIP")] + ["*T*,bad"] + [_line("X").replace("*T*,uuid,terrestrial,2", "*T*,u2,terrestrial,2")]
    f.write_text("\n".join(lines) + "\n")
    d = ais.load_traj(f, min_reports=2)
    assert d.counts["trajectories"] == 3 and d.counts["unparsed_trajectories"] == 1 and d.counts["tracks"] == 2
    tr = d.tracks[0]
    assert np.isnan(tr.vel).all() and np.isnan(tr.sog).all()
    np.testing.assert_allclose(tr.pos, ais.geodetic_to_enu(tr.lonlat[:, 1], tr.lonlat[:, 0]))


def test_moored_discretisation_closed_form() -> None:
    k, q, h = 0.3, 0.02, 7.0
    sde = tl.models.moored(k=torch.tensor(k, dtype=torch.float64), q=torch.tensor(q, dtype=torch.float64))
    with torch.no_grad():
        d = sde(torch.tensor(h, dtype=torch.float64))
    F = np.array([[0, 1], [0, -k]])
    A1 = expm(F * h)
    Q1 = np.array([[q * h, 0], [0, 0]])  # noise enters the position only: Q = q h on x
    A = np.kron(np.eye(2), A1)
    np.testing.assert_allclose(d.A.numpy(), A, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(d.Q.numpy(), np.kron(np.eye(2), Q1), rtol=1e-10, atol=1e-14)
    assert sde.position_indices == (0, 2)
