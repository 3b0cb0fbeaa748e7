"""Tools around the trainer's library: evaluating an exported bundle the way the server does."""
