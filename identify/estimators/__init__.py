"""Estimators: EDMD, closed-loop EDMD (closed form, its SDP, stability-constrained, several
controllers), ARX and closed-loop ARX, and the regression and closed-loop structure they share.
"""
