"""The paper's controlled experiments (``qr-cl reproduce``): the plan, one module per study, the
paper's claims, the report, and the command itself (:mod:`.command`)."""
