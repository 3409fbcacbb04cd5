"""models/rvt"""
