"""mcapio."""
