"""The shipped procedures (YAML), installed as package data so `labrunner run quick` finds them anywhere."""
