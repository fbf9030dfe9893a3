"""``needs_sysid``: the mark of every test that fits an MJCF with mujoco.sysid (an extra)."""

from __future__ import annotations

import pytest

from hilstack.calibration import mjcf_robot as M

try:
    M._sysid()
    HAVE_SYSID = True
except M.SysidNotAvailable:
    HAVE_SYSID = False
needs_sysid = pytest.mark.skipif(not HAVE_SYSID, reason="mujoco.sysid not installed (pip install hilstack[calib])")
