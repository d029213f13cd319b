"""trivla_drake.eval"""
