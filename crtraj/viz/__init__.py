"""The meshcat browser view. Above: io."""
