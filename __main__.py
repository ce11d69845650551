"""``python -m polarstripe``: the command line (tools/cli.py). A Ctrl-C that comes while a command is still
being imported or parsed (a node just started by the launcher) ends it with status 130 and no traceback;
from then on the command handles it (docs/architecture.md "Shutdown")."""

try:
    from polarstripe.tools.cli import main

    status = main()
except KeyboardInterrupt:
    status = 130
raise SystemExit(status)
