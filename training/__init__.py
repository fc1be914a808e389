"""medseg training stage (command-line entry point in `cli.py`)."""
