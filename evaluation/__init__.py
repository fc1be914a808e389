"""medseg evaluation stage (command-line entry point in `cli.py`)."""
