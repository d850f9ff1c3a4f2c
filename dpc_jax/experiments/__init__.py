"""The kit the experiment scripts (``experiments/protocols/``, ``experiments/studies/``) are thin mains over.

What every script shares:

* ``script``: an entry point's plumbing: its parser, the work folder and results page claimed before any
  work, one error line, the progress flag, the timed log line, the table printed and put into its page.
* ``stamp``: the machine, commit, date and Python a figure was measured with.
* ``records``: resumable units of work (a stage, a cell of a grid), one JSON record each with its stamp.
* ``process``: what a command costs, measured from outside its process, and measured stages that run once.
* ``world``: a synthetic world rendered from one seed, and priors with a planted rotation error.
* ``folds``: the protocols' runner: load the config, plan and prepare the folds, train, correct, write.
* ``demos``: the synthetic demo as a study runs it: at a seed, reused when finished, inputs shared.
* ``baselines``: the supervised linear baseline set beside the networks.

What a protocol and a study share, or a study too large for a thin main holds: ``drives`` (the cross-drive
protocol on two real KITTI raw drives), ``comparison`` (the supervised comparison's table), ``scale`` (the
papers' scale on a synthetic stand-in), ``steps`` (a trajectory's steps checked against the images), and the
detection-limit study: ``detection`` (its grid and cells), ``detection_answer`` (what they answer),
``detection_rule`` (where the mean is tested: the options and the rule) and ``detection_page`` (its page).

Nothing else in ``dpc_jax`` imports this package; it builds on the pipelines and everything below them
(``pyproject.toml``'s layers contract).
"""
