"""The console commands: ``aurora-gateway`` and its subcommands (:mod:`~gateway.commands.cli`
is the entry point; the other modules are one subcommand each)."""
