"""KITTI data layer: readers, VO priors, the preprocessing cache and the numpy input pipeline."""
