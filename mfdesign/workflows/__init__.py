"""What each ``mfdesign`` command does, as library functions: load the inputs, fit or
search, write the outputs and figures, and return a small result whose ``summary()`` is
the text the command prints. Units: mm, Pa, N.

The command line (:mod:`mfdesign.cli`) is a shell over these: it parses options, calls ONE
function here and prints its result's ``summary()`` (and its ``warnings`` on stderr). Bad
input raises :class:`mfdesign.errors.InputError` with one line saying what was wrong and
what is allowed (the CLI turns it into exit status 2). Modules here never import
:mod:`mfdesign.cli`.

* :mod:`.plane`: one membrane's simulated force plane (``mfdesign simulate``);
* :mod:`.data`: reading ``DATA``, ``fit``, ``cv`` and ``import``;
* :mod:`.models`: saved model folders (``fit`` / ``fit-mf`` outputs) and the simulator
  constants they stand for;
* :mod:`.space`: design-space bounds (``--thickness-mm`` ...);
* :mod:`.calibrate`: ``calibrate`` and ``fit-mf``;
* :mod:`.diagnose`: ``diagnose``;
* :mod:`.optimize`: ``optimize``;
* :mod:`.propose`: ``propose`` (and the simulator runs it makes);
* :mod:`.demo`: ``demo``, the README's main job (it leaves a campaign, :mod:`mfdesign.campaign`).

Modules are imported on use (``from mfdesign.workflows import optimize``): each holds heavy
dependencies only inside its functions, or at its top when nothing imports it for ``--help``.
"""
