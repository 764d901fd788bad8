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


@pytest.fixture(scope="session", autouse=True)
def _model_cache(tmp_path_factory):
    """Verified model weights go to a temporary folder, not the user's cache."""
    import os

    os.environ["SPIEL_EDGE_MODEL_CACHE"] = str(tmp_path_factory.mktemp("verified-models"))
