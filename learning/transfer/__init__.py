"""Transfer between systems: SIDM domain adaptation, GAT and GARAT grounding (docs/transfer.md)."""
