"""``python -m gateway``: the same as the ``aurora-gateway`` command."""

from gateway.commands.cli import console_main

if __name__ == "__main__":
    console_main()
