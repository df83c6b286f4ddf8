"""What the two drivers truly share: the serial link and the pseudo-terminal helper."""
