"""Liu & Peng 2002: the inverse-dynamics observers' vehicle example and its sweep."""
