"""msmem_analytic: analytic (non-learned) belief models.

``AnalyticObservationModel`` integrates a depth + label frame into the evidential map by exact
voxel ray traversal (the analytic twin of MEM's observation CNABU sigma_o).
"""
