"""``python -m hilstack ...`` is the ``hil`` program (what a process that starts a rig runs)."""

from hilstack.tools.cli import main

main()
