"""cryptoros-certs: certificate provisioning (CA, CSR, signing, encrypted keys, CRL)."""
