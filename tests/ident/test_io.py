import json

import numpy as np
import pytest

from ident.excitation import GBN, generate_multichannel
from ident.io import load_model, register_model, registered_kinds, save_model
from ident.linear import ARX, N4SID, OutputError, StateSpaceModel, StateSpacePEM
from ident.multiple_model import MultipleModel, quantile_edges


def data():
    u = generate_multichannel([GBN(mean_hold_s=2.0), GBN(mean_hold_s=4.0)], 400, 1.0, seed=3)
    y = np.zeros(400)
    for t in range(1, 400):
        y[t] = 0.7 * y[t - 1] + u[t - 1, 0] + 0.3 * u[t - 1, 0] * u[t - 1, 1]
    return u, y + 0.01 * np.random.default_rng(0).standard_normal(400)


MODELS = {
    "arx": lambda u: ARX(2, (2, 1), 1),
    "oe": lambda u: OutputError(2, 2, 1),
    "n4sid": lambda u: N4SID(2, weighting="cva"),
    "ss_pem": lambda u: StateSpacePEM(2, max_nfev=30),
    "multiple_model": lambda u: MultipleModel([1], [quantile_edges(u[:, 1], 2)], local="oe", max_nfev=10),
}


@pytest.mark.parametrize("kind", list(MODELS))
def test_save_load_round_trip(tmp_path, kind):
    u, y = data()
    m = MODELS[kind](u).fit(u, y)
    path = m.save(tmp_path / "model")
    assert path.suffix == ".json" and (tmp_path / "model.npz").exists()
    doc = json.loads(path.read_text())
    assert doc["kind"] == kind
    back = load_model(tmp_path / "model.json")
    assert type(back) is type(m)
    np.testing.assert_array_equal(back.predict(u, y0=y), m.predict(u, y0=y))
    np.testing.assert_array_equal(back.predict_k_step(u, y, 3), m.predict_k_step(u, y, 3))
    assert back.n_params_ == m.n_params_
    assert type(m).load(path) is not None


def test_given_state_space_round_trip(tmp_path):
    m = StateSpaceModel(A=[[0.5]], B=[[1.0, 2.0]], C=[[1.0]], D=[[0.0, 0.1]])
    m.save(tmp_path / "ss.json")
    back = load_model(tmp_path / "ss")
    np.testing.assert_array_equal(back.D_, m.D_)


def test_no_pickle_in_npz(tmp_path):
    u, y = data()
    ARX(1, 1, 1).fit(u, y).save(tmp_path / "m")
    with np.load(tmp_path / "m.npz", allow_pickle=False) as z:
        assert all(z[k].dtype != object for k in z.files)


def test_register_a_new_family(tmp_path):
    @register_model("toy_gain")
    class ToyGain:
        def __init__(self, gain: float = 1.0):
            self.gain = gain

        def _get_state(self):
            return {"gain": self.gain}, {"w": np.array([self.gain])}

        @classmethod
        def _from_state(cls, meta, arrays):
            return cls(gain=float(arrays["w"][0]))

    save_model(ToyGain(2.5), tmp_path / "toy")
    assert load_model(tmp_path / "toy").gain == 2.5
    assert "toy_gain" in registered_kinds()


def test_unknown_kind(tmp_path):
    (tmp_path / "x.json").write_text(json.dumps({"kind": "nope", "module": "os", "meta": {}}))
    with pytest.raises(ValueError, match="unknown model kind"):
        load_model(tmp_path / "x.json")
