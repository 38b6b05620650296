"""Problem files and the versioned result schema, plots. Above: hardware (it composes every section's options)."""
