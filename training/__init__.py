"""Training, evaluation and deployment of policies for the Bioscara tasks (``bioscara`` CLI)."""
