"""Small shared helpers: device choice, atomic file output, hashing."""
