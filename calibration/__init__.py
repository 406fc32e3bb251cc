"""Camera models, camera files, and frames & transforms (T_a_b, check_T)."""
