"""trivla_drake.robot"""
