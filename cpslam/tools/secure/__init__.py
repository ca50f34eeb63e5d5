"""`cpslam secure init`: a certificate authority, certificates per role and the Zenoh access
control that binds each agent's certificate to its own key expressions."""
