"""svolsdf.render"""
