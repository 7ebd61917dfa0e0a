"""cryptoros-authz: the authorization registry and RS256 access-token issuer."""
