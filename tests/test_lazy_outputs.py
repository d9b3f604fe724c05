"""Camera renders compute only the outputs that are read (issue 10)."""

from __future__ import annotations

import pytest
import torch

from seathru_nerfstudio.lazy_outputs import LazyOutputs
from seathru_nerfstudio.viewer import DISPLAY_OUTPUTS

from test_model import small_camera
from tiny_training import spy_calls, tiny_model


def test_lazy_outputs_compute_on_first_read_only_and_keep_what_was_set():
    calls = []

    def compute(name, outputs):
        calls.append(name)
        if name == "double":
            return {"double": outputs["one"] * 2}
        return {"one": torch.ones(1), "two": torch.full((1,), 2.0)}

    lazy = LazyOutputs(["one", "two", "double"], compute)
    assert list(lazy) == ["one", "two", "double"] and len(lazy) == 3 and "two" in lazy
    assert calls == [] and lazy.computed() == []
    assert float(lazy["double"]) == 2.0
    assert calls == ["double", "one"]  # "two" came along with "one"
    assert float(lazy["two"]) == 2.0 and calls == ["double", "one"]
    lazy["extra"] = torch.zeros(1)
    assert "extra" in lazy and list(lazy)[-1] == "extra"
    with pytest.raises(KeyError):
        lazy["missing"]


class Counter:
    """Counts the calls of the object field and of the medium of a model (test spies)."""

    def __init__(self, model):
        self.field_calls = spy_calls(model.field)
        self.medium_calls = spy_calls(model.medium_field)

    def take(self):
        counts = (len(self.field_calls), len(self.medium_calls))
        self.field_calls.clear()
        self.medium_calls.clear()
        return counts


@pytest.fixture
def model():
    torch.manual_seed(0)
    model = tiny_model(eval_num_rays_per_chunk=64)  # 16x12 = 192 rays: 3 chunks
    model.eval()
    return model


def test_an_output_that_was_not_read_is_not_computed(model):
    counter = Counter(model)
    chunks = 3
    out = model.get_outputs_for_camera(small_camera())
    assert counter.take() == (0, 0)  # listing the outputs renders nothing
    assert tuple(out)[: len(DISPLAY_OUTPUTS)] == DISPLAY_OUTPUTS

    out["rgb_display"]  # the viewer's first view: field and medium once per chunk ...
    assert counter.take() == (chunks, chunks)
    out["depth"], out["clean"], out["accumulation"]  # ... the object outputs came along
    assert counter.take() == (0, 0)
    assert "medium_attenuation" not in out.computed()  # ... the medium maps did not
    out["medium_attenuation_display"]  # the medium maps: the medium alone
    assert counter.take() == (0, chunks)

    clean = model.get_outputs_for_camera(small_camera())
    clean["clean_display"], clean["depth"]  # clean view: no medium at all
    assert counter.take() == (chunks, 0)
    model.viewer_controls.c1_water.value = False  # Water off: rgb_display shows clean
    off = model.get_outputs_for_camera(small_camera())
    off["rgb_display"]
    assert counter.take() == (chunks, 0)


def test_lazy_outputs_equal_the_full_render(model):
    full = model.get_outputs_for_camera(small_camera())
    with torch.enable_grad():  # read as ns-render reads them: outside no_grad
        everything = {name: full[name] for name in full}  # reads every output
    assert not any(value.requires_grad for value in everything.values())
    with torch.no_grad():
        flat = model(small_camera().generate_rays(camera_indices=0).flatten())
    for name in ("rgb", "clean", "depth", "accumulation", "medium_attenuation", "backscatter"):
        torch.testing.assert_close(everything[name].reshape(flat[name].shape), flat[name], msg=name)
    alone = model.get_outputs_for_camera(small_camera())
    torch.testing.assert_close(alone["clean"], everything["clean"])  # without the medium: same clean
    torch.testing.assert_close(alone["depth"], everything["depth"])


def test_clear_air_renders_call_no_medium(model):
    clear = tiny_model(medium_model="none", eval_num_rays_per_chunk=64)
    clear.eval()
    counter = Counter(clear)
    out = clear.get_outputs_for_camera(small_camera())
    names = list(out)
    values = {name: out[name] for name in names}
    assert counter.take()[1] == 0
    assert bool((values["backscatter"] == 0).all()) and bool((values["medium_attenuation"] == 0).all())
    torch.testing.assert_close(values["rgb"], values["clean"])
