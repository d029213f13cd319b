"""trivla_drake.station"""
