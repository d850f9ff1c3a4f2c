"""What ``experiments/studies/linear_baseline.py`` fits on and sets its figures beside.

``SEQUENCES``: the libviso2 sequences held out in turn (KITTI odometry 00, 02, 05–10, as
``../shared/data/kitti-libviso2`` holds them: ``stereo_XX.mat``, ``mono_XX.mat``).

``PUBLISHED``: the papers' rows for the same sequences (seg. t %, seg. r °/100 m, m-ATE m, m-ATE °).
libviso2-s and ss-DPC-Net (self-supervised; "best loss" and "loop closure" epoch selection) are the
ss-DPC-Net authors' released results table (github.com/utiasSTARS/ss-dpc-net,
``paper_plots_and_data/stereo_results_kitti.csv`` and ``mono_results_kitti.csv``); DPC-Net (supervised,
Peretroukhin & Kelly 2018) is the row the same release's ``generate_stereo_results.py`` lists for 00, 02
and 05. Zhang et al. (Stereo DPC, Sensors 2021) are not included: their tables could not be read from the
sources available here.
"""

SEQUENCES = ("00", "02", "05", "06", "07", "08", "09", "10")

PUBLISHED: dict[str, dict[str, tuple[float, float, float, float]]] = {
    "stereo": {
        "00 libviso2-s": (2.791, 1.292, 53.766, 13.301),
        "00 + DPC-Net (supervised)": (1.62, 0.559, 15.68, 3.07),
        "00 + ss-DPC-Net, best loss": (0.991, 0.457, 12.589, 2.469),
        "00 + ss-DPC-Net, loop closure": (1.033, 0.444, 14.654, 3.322),
        "02 libviso2-s": (2.417, 0.923, 68.604, 12.554),
        "02 + DPC-Net (supervised)": (1.16, 0.436, 17.69, 2.86),
        "02 + ss-DPC-Net, best loss": (1.108, 0.499, 15.687, 3.524),
        "02 + ss-DPC-Net, loop closure": (0.83, 0.373, 21.308, 1.907),
        "05 libviso2-s": (2.313, 1.135, 19.677, 6.298),
        "05 + DPC-Net (supervised)": (1.34, 0.562, 9.82, 3.57),
        "05 + ss-DPC-Net, best loss": (1.327, 0.597, 10.924, 4.097),
        "05 + ss-DPC-Net, loop closure": (0.829, 0.304, 4.034, 1.178),
    },
    "mono": {
        "09 libviso2-m": (8.666, 2.755, 81.345, 15.4),
        "09 + ss-DPC-Net, best loss": (2.824, 0.757, 16.369, 3.46),
        "09 + ss-DPC-Net, loop closure": (2.132, 0.803, 11.129, 3.887),
        "10 libviso2-m": (7.991, 3.317, 51.633, 16.454),
        "10 + ss-DPC-Net, best loss": (3.806, 1.343, 13.038, 3.367),
        "10 + ss-DPC-Net, loop closure": (3.479, 1.377, 11.947, 3.515),
    },
}
