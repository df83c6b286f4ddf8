"""Driver of the OriginMan expansion board (Hiwonder RRC Lite firmware family)."""
