"""Model Discrepancy Explorer app (Panel + HoloViews), installed as ``mdcore_app``."""
