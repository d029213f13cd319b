"""trivla_drake.nn"""
