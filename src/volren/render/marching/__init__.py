"""Light-map ray marching: DSSRM (the baseline), CMSRM (paper 001), CACRM with VSA and interleaving (paper 000 §3.1)."""
