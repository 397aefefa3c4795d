//! Point and observation tables of the command line (CSV with a header).
