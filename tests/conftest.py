import numpy as np
import pytest

from spiel_edge.profile.schema import load_profile


@pytest.fixture(scope="session")
def profile():
    return load_profile("spiel-icra23")


@pytest.fixture(scope="session")
def subset():
    from spiel_edge.data import load_subset

    return load_subset()


@pytest.fixture
def rng():
    return np.random.default_rng(1234)
