"""The ``mfdesign`` command line (typer): one module per command, a thin shell over the
library. Units: mm, Pa, N.

A command parses its options, calls ONE library function (mostly of
:mod:`mfdesign.workflows`) and prints that function's ``summary()``; command modules share
only the private helpers here (``_app``, ``_contract``, ``_runlog``, ``_space``), never
each other.

Every command module defines ``register(app)`` and imports its heavy dependencies (JAX,
emcee, ...) inside the command bodies, so that ``mfdesign --help`` stays fast. The
contract (:mod:`._contract`): bad input prints one line and exits with status 2; anything
else names a log file with the traceback and exits with status 1.
"""

from mfdesign.cli import (
    _contract,
    calibrate,
    campaign,
    data,
    demo,
    diagnose,
    discriminate,
    optimize,
    propose,
    rig,
    simulate,
)
from mfdesign.cli._app import app, plain_help

__all__ = ["app"]

# Registration order is the order of ``mfdesign --help``.
for _module in (simulate, demo, campaign, data, rig, calibrate, diagnose, discriminate, propose, optimize):
    _module.register(app)
_contract.apply(app)  # every command: --out checked and locked before computing
plain_help(app)  # every command, sub-apps too: brackets shown as written, the design key and units
