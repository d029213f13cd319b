"""trivla_drake.data"""
