"""The commands of `main.py` (app/cli.py dispatches): one module each, with its `run(args)`."""
