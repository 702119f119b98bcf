"""The ``zfusion`` commands, one module each: ``register(subparsers)`` adds its
sub-parser (and sets itself as what runs), ``run(args)`` runs it.

A command module is light: it imports :mod:`.options` and names the modules that do the
work with :func:`fusion.lazy.lazy`, so they load only when the command runs. Adding a
command is one module here and one line in :data:`services.cli.COMMANDS`.
"""
