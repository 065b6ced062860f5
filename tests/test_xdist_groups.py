"""`make test` runs under `--dist loadgroup`: a test marked `xdist_group` must carry its group in its node
id, or the scheduler spreads the group over both workers and every group fixture is built twice."""

import pytest


@pytest.mark.xdist_group("probe")
def test_a_grouped_test_carries_its_group_under_loadgroup(request):
    if not getattr(request.config.option, "loadgroup", False):
        pytest.skip("not an xdist worker under --dist loadgroup")
    assert request.node.nodeid.endswith("@probe"), request.node.nodeid
