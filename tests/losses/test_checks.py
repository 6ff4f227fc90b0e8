"""Input checks of the losses: sample names, class ids, unit-interval targets, the depth unit warning."""
import warnings

import pytest
import torch

from omnidl.losses.checks import (DepthUnitCheck, as_class_ids, require_nonempty_maps, require_unit_interval,
                                  sample_names)


def test_sample_names_from_meta():
    batch = {"meta": [{"name": "a"}, {"image": "x/b.png"}, {"file": "c.txt"}, {"index": 7}, "junk"]}
    assert sample_names(batch) == ["a", "x/b.png", "c.txt", "7", "#4"]
    assert sample_names(batch, [1]) == ["x/b.png"]
    assert sample_names({}) == [] and sample_names(None) == []


def test_class_ids_fast_path_and_ignore_index_outside_the_range():
    y = torch.tensor([[[0, 1], [2, 3]]], dtype=torch.uint8)
    out = as_class_ids(y, 4, 0, "t")
    assert out.dtype == torch.int64 and torch.equal(out, y.long())
    void = torch.tensor([[[255, 1], [2, 3]]])
    assert torch.equal(as_class_ids(void, 4, 255, "t"), void)     # the ignore index may lie outside [0, C)
    with pytest.raises(ValueError, match=r"\[255\].*ignore index 0"):
        as_class_ids(void, 4, 0, "t")
    assert as_class_ids(torch.zeros(0, 3, 4), 4, 0, "t").shape == (0, 3, 4)


def test_class_ids_error_lists_values_and_samples():
    y = torch.arange(40).reshape(2, 4, 5)
    listed = r"\[14, 15, 16, 17, 18, 19, 20, 21, \.\.\.\] outside \[0, 14\).*sample\(s\) a, b"
    with pytest.raises(ValueError, match=listed):
        as_class_ids(y, 14, 0, "t", batch={"meta": [{"name": "a"}, {"name": "b"}]})
    with pytest.raises(ValueError, match=r"batch item\(s\) 1"):
        as_class_ids(torch.tensor([[[1]], [[20]]]), 14, 0, "t")


def test_unit_interval_names_integer_maps():
    require_unit_interval(torch.rand(2, 1, 4, 4), "t", "k")
    require_unit_interval(torch.zeros(0, 1, 4, 4), "t", "k")
    with pytest.raises(ValueError, match=r"from 0 to 255.*integer torch.uint8 map"):
        require_unit_interval(torch.tensor([0, 255], dtype=torch.uint8).view(1, 1, 1, 2), "t", "k")


def test_nonempty_maps_allows_an_empty_batch():
    require_nonempty_maps(torch.zeros(0, 1, 0, 4), "x", "t")
    with pytest.raises(ValueError, match=r"zero-size map \(1, 1, 0, 4\)"):
        require_nonempty_maps(torch.zeros(1, 1, 0, 4), "x", "t")


def test_depth_unit_check_fp16_large_map_no_false_alarm():
    """A 256x512 half-precision map of 3 m sums past the fp16 range: the check must not call that > 1000 m."""
    target = torch.full((1, 1, 256, 512), 3.0, dtype=torch.float16)
    check = DepthUnitCheck("t")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check(target.clone(), target, target > 0)
    assert not check.warned


def test_depth_unit_check_warns_once_per_instance():
    target = torch.full((1, 1, 4, 4), 3000.0)
    check = DepthUnitCheck("t")
    with pytest.warns(UserWarning, match="not in metres"):
        check(target, target, target > 0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check(target, target, target > 0)
    with pytest.warns(UserWarning, match="not in metres"):
        DepthUnitCheck("t")(target, target, target > 0)          # a new loss instance warns again
