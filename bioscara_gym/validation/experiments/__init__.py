"""One module per kind of recording: a replay of its program and a comparison."""
