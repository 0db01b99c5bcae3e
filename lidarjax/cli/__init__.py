"""The ``lidarjax`` command line (console script ``lidarjax = lidarjax.cli:main``).

Subcommands: ``info``, ``datasets``, ``fetch``, ``map``, ``localize``, ``polylines``,
``planes``, ``poles`` and ``experiment``; ``lidarjax COMMAND --help`` describes each with an
example. Like ``experiments/``, this is one of the places that know configurations; the
library never imports it. Every computing subcommand turns on JAX's persistent
compilation cache (:func:`lidarjax.enable_compilation_cache`) first.

``lidarjax --host-devices N COMMAND`` (or ``$LIDARJAX_HOST_DEVICES``) exposes the CPU as
N JAX devices before JAX starts (:func:`lidarjax.distributed.use_host_devices`), e.g. for
a particle filter sharded over the cores; ``lidarjax info`` prints the device count.

Exit status: 0 on success, 2 for bad input (a usage error, or a missing or corrupt file:
one line naming the argument), 1 for other failures (``--debug`` shows the traceback).
"""

from ._inputs import CliInputError as CliInputError
from ._main import build_parser as build_parser
from ._main import main as main

__all__ = ["CliInputError", "build_parser", "main"]
