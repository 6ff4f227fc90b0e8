"""Loss tests (a package, so that test_depth.py / test_segmentation.py may share basenames with tests/metrics/)."""
