"""The example camera held to sssphase's device conformance checks, as a plugin's own suite runs them
(``pytest examples/sssphase-example-plugin/tests``; sssphase's own suite holds it to the same checks)."""

from sssphase_example_plugin import sssphase_cameras

from sssphase_plugins.conformance import check_driver


def test_the_test_pattern_camera_follows_the_camera_protocol():
    (provider,) = sssphase_cameras()
    (info,) = provider.discover()
    check_driver("camera", lambda: provider.open(info.id, {"example": {"width": 64, "height": 48}}, {}))
