"""svolsdf.ibr"""
