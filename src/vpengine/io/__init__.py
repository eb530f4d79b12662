"""Sources and sinks: frames in, results out."""
