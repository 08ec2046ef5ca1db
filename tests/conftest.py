import pytest

from pomil.demos import record_circles_demos
from pomil.envs.circles import make_spec


@pytest.fixture(scope="session")
def spec():
    return make_spec()


@pytest.fixture(scope="session")
def demos(spec):
    return record_circles_demos(spec, 200, seed=0)


@pytest.fixture(scope="session")
def demos_path(demos, tmp_path_factory):
    path = tmp_path_factory.mktemp("data") / "circles.npz"
    demos.save(path)
    return path
