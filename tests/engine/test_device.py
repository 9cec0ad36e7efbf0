"""``engine.device.resolve_device``: specs map to Warp devices; a Warp device is returned as it is."""

from __future__ import annotations

import numpy as np
import pytest

from engine.device import resolve_device


def test_a_warp_device_is_returned_as_is(device):
    """Warp 1.19 has no ``wp.context``: the check names ``wp.Device``, so a device object passes straight through."""
    import warp as wp

    dev = wp.get_device(device)
    assert resolve_device(dev) is dev
    assert resolve_device(device) is dev


def test_reconstruct_takes_a_warp_device(device):
    import warp as wp

    from engine.params import ReconParams
    from engine.job.pipeline import reconstruct
    from engine.types import Volume

    z, y, x = np.mgrid[:20, :20, :20].astype(np.float32)
    ball = Volume(6.0 - np.sqrt((z - 9.5) ** 2 + (y - 9.5) ** 2 + (x - 9.5) ** 2), (1.0, 1.0, 1.0))
    params = ReconParams.from_dict({"iso": {"iso": 0.0}, "body": None})
    by_object = reconstruct(ball, params, device=wp.get_device(device))
    by_name = reconstruct(ball, params, device=device)
    assert by_object.report["device"]["name"] == str(wp.get_device(device))
    assert by_object.report["device"]["spec"] == str(wp.get_device(device))  # the report stays JSON-able
    np.testing.assert_array_equal(by_object.mesh.faces, by_name.mesh.faces)
    np.testing.assert_array_equal(by_object.mesh.vertices, by_name.mesh.vertices)


@pytest.mark.parametrize("spec", ["tpu", "cuda:x", "", 3, None])
def test_a_malformed_spec_is_refused(spec):
    with pytest.raises(ValueError, match="Expected device"):
        resolve_device(spec)
