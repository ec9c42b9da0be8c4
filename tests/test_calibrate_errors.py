"""issue 23, item 6: calibrate maps only the fits' own refusals (bad input) to the user-error type
(exit 2); any other ValueError raised inside a fit is a bug and propagates with its traceback."""

from types import SimpleNamespace

import numpy as np
import pytest

from fluxcli.calibration.mirrors import MirrorFitError
from fluxcli.errors import UserError
from fluxcli.stages import calibrate as S
from fluxcli.structured.calibrate import ProjectorFitError, calibrate_projector


def _mirror_inputs():
    src = SimpleNamespace(grid=SimpleNamespace(pitch_mm=5.0, shape=(3, 3)), heights_mm=[0.0, 10.0])
    mirror = SimpleNamespace(center_mm=[0, 0, 0], normal=[1, 0, 0], axis=[0, 0, 1], size_mm=(10, 10), name="m")
    ctx = SimpleNamespace(say=lambda msg: None)
    return src, SimpleNamespace(mirrors=[mirror]), SimpleNamespace(camera=None), [np.zeros((4, 4))] * 2, ctx


@pytest.mark.parametrize("raised, expected", [(MirrorFitError("only 3 grid points were matched"), UserError),
                                              (ValueError("operands could not be broadcast"), ValueError)])
def test_a_mirror_fit_refusal_is_a_user_error_and_a_numpy_bug_is_not(monkeypatch, raised, expected):
    def fit(*a, **kw):
        raise raised

    monkeypatch.setattr(S, "refine_mirrors", fit)
    with pytest.raises(expected) as info:
        S._mirrors(*_mirror_inputs())
    assert (info.type is UserError) == (expected is UserError)  # a bug is not dressed up as bad input
    if expected is UserError:
        assert "system.mirrors[0]" in str(info.value) and "only 3 grid points" in str(info.value)


def test_too_few_board_points_is_the_projector_fit_s_own_refusal():
    """The one input error calibrate_projector reports is a ProjectorFitError (still a ValueError)."""
    X = np.zeros((3, 3))
    xy = np.zeros((3, 2))
    col = row = np.full((8, 8), np.nan)
    with pytest.raises(ProjectorFitError, match="board point"):
        calibrate_projector([(X, xy, col, row)], width_px=64, height_px=32, gamma=1.0)
