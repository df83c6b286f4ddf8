"""Driver for the drone handset control link (frames from the handset's radio modem)."""
